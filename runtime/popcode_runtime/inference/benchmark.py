"""Latency of a model on this device: warm-up, then percentiles of many timed calls.

Used by ``popcode bench`` and by ``bench/latency``; numbers, never assertions.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from functools import cache, partial

import numpy as np
import onnxruntime as ort

from ..base.checks import integer
from .estimator import PoseEstimator

BENCH_IMAGE_SHAPE = (540, 720)  # T-LESS Primesense resolution, (H, W)
MAX_BENCH_BATCH = 1024  # a batch's crops and outputs are held at once
MAX_BENCH_ITERATIONS, MAX_BENCH_WARMUP = 10_000, 1_000  # per row: a benchmark ends in bounded time


@dataclass(frozen=True)
class LatencyStats:
    """Percentiles of per-call latency and the implied throughput."""

    stage: str  # "end-to-end" (crop + inference + decode) or "inference"
    batch: int
    threads: int
    median_ms: float
    p90_ms: float
    p99_ms: float
    mean_ms: float
    iterations: int
    crops_per_s: float

    def to_dict(self) -> dict:
        return asdict(self)


def time_calls(call: Callable[[], object], warmup: int, iterations: int) -> np.ndarray:
    """Per-call wall times in milliseconds, after ``warmup`` untimed calls."""
    for _ in range(warmup):
        call()
    times = np.empty(iterations)
    for index in range(iterations):
        started = time.perf_counter()
        call()
        times[index] = (time.perf_counter() - started) * 1e3
    return times


def summarize(times_ms: np.ndarray, stage: str, batch: int, threads: int) -> LatencyStats:
    median = float(np.median(times_ms))
    return LatencyStats(
        stage=stage,
        batch=batch,
        threads=threads,
        median_ms=median,
        p90_ms=float(np.percentile(times_ms, 90)),
        p99_ms=float(np.percentile(times_ms, 99)),
        mean_ms=float(np.mean(times_ms)),
        iterations=len(times_ms),
        crops_per_s=batch * 1e3 / median,
    )


def synthetic_scene(batch: int, rng: np.random.Generator) -> tuple[np.ndarray, list[list[float]]]:
    """A random grey uint8 image and ``batch`` object-sized boxes inside it."""
    height, width = BENCH_IMAGE_SHAPE
    image = rng.integers(0, 256, size=(height, width), dtype=np.uint8)
    boxes = []
    for _ in range(batch):
        w, h = rng.uniform(60, 200, size=2)
        boxes.append([float(rng.uniform(0, width - w)), float(rng.uniform(0, height - h)), float(w), float(h)])
    return image, boxes


def benchmark_estimator(
    estimator: PoseEstimator,
    batch_sizes: Sequence[int] = (1, 8, 32),
    warmup: int = 10,
    iterations: int = 100,
    threads: int = 0,
    seed: int = 0,
) -> list[LatencyStats]:
    """End-to-end and inference-only latency for each batch size."""
    for batch in batch_sizes:
        integer(batch, "batch size", 1, MAX_BENCH_BATCH)
    warmup = integer(warmup, "warmup calls", 0, MAX_BENCH_WARMUP)
    iterations = integer(iterations, "timed calls (iterations)", 1, MAX_BENCH_ITERATIONS)
    rng = np.random.default_rng(seed)
    K = [1075.65, 1073.90, 360.0, 270.0]  # any valid camera; only allocentric models use it
    results = []
    for batch in batch_sizes:
        image, boxes = synthetic_scene(batch, rng)
        crops = estimator.crops(image, boxes)
        end_to_end = time_calls(partial(estimator.predict, image, boxes, K=K), warmup, iterations)
        inference = time_calls(partial(estimator.run, crops), warmup, iterations)
        results.append(summarize(end_to_end, "end-to-end", batch, threads))
        results.append(summarize(inference, "inference", batch, threads))
    return results


# CPU features that change how fast the convolutions and int8 kernels run (and, for training, whether torch
# computes in bf16: avx512_bf16 / amx_bf16).
CPU_FLAGS = ("avx2", "fma", "avx512f", "avx512_vnni", "avx_vnni", "avx512_bf16", "amx_tile", "amx_bf16", "neon",
             "asimd")


def parse_cpuinfo(lines: Iterable[str]) -> tuple[str | None, frozenset[str]]:
    """The model name and the feature flags of the first processor in ``/proc/cpuinfo``'s lines (x86 lists
    them as ``flags``, Arm as ``Features``)."""
    model, flags = None, frozenset()
    for line in lines:
        key, _, value = line.partition(":")
        if key.strip() == "model name" and model is None:
            model = value.strip()
        elif key.strip() in ("flags", "Features") and not flags:
            flags = frozenset(value.split())
    return model, flags


@cache
def cpu_info() -> tuple[str | None, frozenset[str]]:
    """This CPU's model name and every feature flag (``None`` and none where Linux's list is missing)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as handle:
            return parse_cpuinfo(handle)
    except OSError:
        return None, frozenset()


def machine_description() -> dict:
    """What the numbers were measured on: CPU model and its relevant flags (Linux), cores, versions."""
    cpu, present = cpu_info()
    flags = [flag for flag in CPU_FLAGS if flag in present]
    return {
        "cpu": cpu or platform.processor() or platform.machine(),
        "cpu_flags": flags,
        "cores": os.cpu_count(),
        "system": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "numpy": np.__version__,
        "onnxruntime": ort.__version__,
    }
