"""Runtime latency against the memory-bandwidth floor: fp32, the quantised variants and torch eager.

    python -m bench.latency [--quick] [--out DIR] [--networks paper small]

Random weights (timing does not depend on them). Per network, variant, thread
count (1 and all cores) and batch (1, 8, 32): end-to-end (crop + inference +
argmax decode) and inference-only percentiles, from the runtime's own
``benchmark_estimator``; torch eager on the same weights times the trainer's
torch engine through the same ``PoseEstimator.run``.

The floor of a variant is the bytes of its weights (every initializer of its
graph, which one forward pass must read) over the memory read bandwidth
measured here with the same number of threads (numpy sums over a large
array, best of several). The output layer's share comes from onnxruntime's
profiler (node times of ``/head/`` nodes over all node times, batch 1).
Argmax and pose agreement of the quantised variants with fp32 are measured on
crops of rendered built-in objects; with random weights they say how much
quantisation moves the peak of an untrained code, which is a harder test than
a trained code's clear peak, but not the same one. The model is of one object
without symmetry, so the pose agreement (same decoded rotation within one
grid step, see ``popcode_trainer.export.agreement.pose_agreement``) differs from the
argmax agreement only by peaks that moved to a grid neighbour. int8 is
calibrated on the even crops; agreement is measured on the odd ones. The compute floor is the MACs
over the GEMM peak measured here (a 1024^3 MatMul, best of several): an
estimate, not a strict bound -- with the cores shared, the 2-thread peak is
depressed and some 2-thread rows fall below 1x.

Findings (what the numbers say, and why the int8 recipe): [results/latency-findings.md](results/latency-findings.md).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from popcode_runtime.coding.population_code import CodeLayout
from popcode_runtime.inference.benchmark import benchmark_estimator, summarize, time_calls
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.model.decoding import DECODERS, decode_output
from popcode_runtime.model.engine import OnnxEngine, onnx_session
from popcode_runtime.model.metadata import INPUT_NAME, ModelMetadata, Representation
from popcode_trainer.data.render import render_builtin_split
from popcode_trainer.demo.steps import SMALL_NETWORK
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.export.agreement import compare
from popcode_trainer.export.model_io import ONNX_IR_VERSION
from popcode_trainer.export.onnx_export import ONNX_OPSET, export_onnx
from popcode_trainer.export.quantise import quantise
from popcode_trainer.export.torch_engine import TorchEngine
from popcode_trainer.train.config import Config
from popcode_trainer.train.network import NetworkConfig, PopcodeNet, count_macs, count_parameters
from popcode_trainer.train.training_data import validation_crops
from tools.command import run_command
from tools.report import machine, machine_line, write_results

QUANTISED = {"int8-static": "int8", "nbits4": "nbits4", "nbits8": "nbits8"}  # variant -> quantise.quantise kind
BATCHES = (1, 8, 32)


@dataclass(frozen=True)
class Network:
    """A benchmarked network: its shape and the code layout its output encodes."""

    config: NetworkConfig
    layout: CodeLayout


NETWORKS = {
    "paper": Network(NetworkConfig(), CodeLayout()),
    # The paper's code and MLP on a 10x cheaper trunk: what the trunk costs (the paper's 3.2 ms on M1).
    "light": Network(NetworkConfig(conv_channels=(32, 64, 128)), CodeLayout()),
    "small": Network(NetworkConfig(output_dim=642 * 36, conv_channels=(32, 64, 64), squeeze_channels=16,
                                   hidden=(256, 256, 256)), CodeLayout(n_axes=642)),
    # The quick recipe's networks (pipeline.SMALL_NETWORK and its residual trunk): the accuracy-latency frontier.
    "quick-paper-trunk": Network(replace(SMALL_NETWORK, output_dim=642 * 36, trunk="paper", conv_channels=(16, 32, 32)),
                                 CodeLayout(n_axes=642)),
    "quick-residual": Network(replace(SMALL_NETWORK, output_dim=642 * 36), CodeLayout(n_axes=642)),
    "tiny": Network(NetworkConfig(output_dim=42 * 12, conv_channels=(8, 8, 8), squeeze_channels=4,
                                  hidden=(32, 32, 32)), CodeLayout(n_axes=42, n_angles=12, sigma_deg=30.0)),
}


@dataclass(frozen=True)
class Budget:
    """How long to measure: timed calls per batch size, warm-up calls, bandwidth array and repeats."""

    iterations: dict[int, int]
    warmup: int
    bandwidth_mb: int
    bandwidth_repeats: int
    profile_runs: int
    render_per_object: int
    peak_repeats: int


FULL = Budget({1: 100, 8: 15, 32: 6}, warmup=5, bandwidth_mb=512, bandwidth_repeats=7, profile_runs=30,
              render_per_object=40, peak_repeats=10)
QUICK = Budget({1: 5, 8: 2, 32: 2}, warmup=1, bandwidth_mb=64, bandwidth_repeats=2, profile_runs=2,
               render_per_object=1, peak_repeats=1)
GEMM_SIDE = 1024  # the peak is measured on a square GEMM this size


def read_bandwidth_gb_s(threads: int, megabytes: int, repeats: int) -> float:
    """Memory read bandwidth [GB/s]: ``threads`` numpy sums over slices of one large array, best run."""
    array = np.ones(megabytes * 2**20 // 8)  # written once, so every page is resident
    chunks = np.array_split(array, threads)
    best = np.inf
    with ThreadPoolExecutor(threads) as pool:  # numpy releases the GIL inside the sum
        for _ in range(repeats):
            started = time.perf_counter()
            list(pool.map(np.sum, chunks))
            best = min(best, time.perf_counter() - started)
    return array.nbytes / best / 1e9


def _gemm_model(integer: bool) -> bytes:
    """One ``[M, K] x [K, K]`` MatMul (fp32) or MatMulInteger (uint8 x int8, what static int8 runs)."""
    rng = np.random.default_rng(0)
    weight = (rng.integers(-64, 64, (GEMM_SIDE, GEMM_SIDE), dtype=np.int8) if integer
              else rng.standard_normal((GEMM_SIDE, GEMM_SIDE), dtype=np.float32))
    x = helper.make_tensor_value_info("x", TensorProto.UINT8 if integer else TensorProto.FLOAT, ["M", GEMM_SIDE])
    y = helper.make_tensor_value_info("y", TensorProto.INT32 if integer else TensorProto.FLOAT, ["M", GEMM_SIDE])
    node = helper.make_node("MatMulInteger" if integer else "MatMul", ["x", "w"], ["y"])
    graph = helper.make_graph([node], "gemm", [x], [y], [numpy_helper.from_array(weight, "w")])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", ONNX_OPSET)])
    model.ir_version = ONNX_IR_VERSION
    return model.SerializeToString()


def gemm_peak_gmac_s(threads: int, integer: bool, repeats: int) -> float:
    """Multiply-accumulates per second [GMAC/s] of onnxruntime's GEMM on this CPU, best of ``repeats``.

    The compute floor of a network is its MACs over this: the 5x5 convs run
    as GEMMs (im2col) and cannot beat it, whatever the memory bandwidth.
    """
    session = onnx_session(_gemm_model(integer), threads=threads)
    x = (np.random.default_rng(1).integers(0, 256, (GEMM_SIDE, GEMM_SIDE)).astype(np.uint8) if integer
         else np.random.default_rng(1).standard_normal((GEMM_SIDE, GEMM_SIDE), dtype=np.float32))
    best = min(time_calls(partial(session.run, None, {"x": x}), 1, repeats))
    return GEMM_SIDE**3 / (best * 1e-3) / 1e9


def weight_bytes(path: Path) -> int:
    """Bytes of every initializer of an ONNX graph: what one forward pass reads at least once."""
    graph = onnx.load(str(path), load_external_data=False).graph
    return sum(int(np.prod(init.dims, dtype=np.int64)) * helper.tensor_dtype_to_np_dtype(init.data_type).itemsize
               for init in graph.initializer)


def node_shares(path: Path, crops: np.ndarray, threads: int, runs: int, work: Path) -> dict[str, float]:
    """Shares of node time in the output layer (``/head/`` nodes) and in convolutions, from onnxruntime's profiler."""
    session = onnx_session(path, threads=threads, profile_prefix=str(work / f"profile-{path.stem}-{threads}"))
    for _ in range(runs):
        session.run(None, {INPUT_NAME: crops})
    events = json.loads(Path(session.end_profiling()).read_text(encoding="utf-8"))
    nodes = [e for e in events if e.get("cat") == "Node" and e["name"].endswith("_kernel_time")]
    total = sum(e["dur"] for e in nodes) or float("nan")
    head = sum(e["dur"] for e in nodes if "/head/" in e["name"])
    convs = sum(e["dur"] for e in nodes if "Conv" in e["args"].get("op_name", ""))  # Conv, QLinearConv, FusedConv
    return {"output_layer_share": head / total, "conv_share": convs / total}


def rendered_crops(work: Path, per_object: int, size: int) -> np.ndarray:
    """Crops ``(N, 1, S, S)`` of the rendered built-in objects: real-ish input for the agreement with fp32."""
    split = render_builtin_split(work / "render", per_object, seed=1)
    config = Config.from_dict({"data": {"splits": [str(split)], "models_dir": str(split / "models"),
                                        "val_fraction": 0.0, "crop_size": size, "num_workers": 0}})
    return validation_crops(config, count=10_000)[0]  # no validation share: every instance


def export_variants(name: str, network: Network, calibration: np.ndarray,
                    work: Path) -> tuple[PopcodeNet, ModelMetadata, dict[str, Path]]:
    """Random-weight model in eval mode, its metadata and its fp32 + quantised ONNX files (int8 calibrated on
    ``calibration``)."""
    torch.manual_seed(0)
    model = PopcodeNet(network.config).eval()
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE, code=network.layout,
                             objects={1: {"diameter": 100.0}}, input_size=network.config.input_size)
    fp32 = export_onnx(model, metadata, work / f"{name}.onnx")
    variants = {v: quantise(fp32, kind, metadata, calibration) for v, kind in QUANTISED.items()}
    return model, metadata, {"fp32": fp32, **variants}


def torch_stats(model: PopcodeNet, metadata: ModelMetadata, crops: np.ndarray, threads: int,
                budget: Budget) -> list[dict[str, Any]]:
    """Inference-only latency of torch eager (the trainer's torch engine in the runtime's ``PoseEstimator.run``,
    as the runtime rows time onnxruntime) with ``threads`` intra-op threads."""
    estimator = PoseEstimator.from_engine(TorchEngine(model), metadata)
    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        rows = []
        for batch in BATCHES:
            x = np.ascontiguousarray(crops[:1].repeat(batch, axis=0))
            times = time_calls(partial(estimator.run, x), budget.warmup, budget.iterations[batch])
            rows.append(summarize(times, "inference", batch, threads).to_dict())
    finally:
        torch.set_num_threads(previous)
    return rows


def runtime_stats(path: Path, threads: int, budget: Budget) -> list[dict[str, Any]]:
    """End-to-end and inference latency of the runtime's ``PoseEstimator`` for every batch size."""
    estimator = PoseEstimator(path, threads=threads)
    return [stats.to_dict() for batch in BATCHES
            for stats in benchmark_estimator(estimator, (batch,), budget.warmup, budget.iterations[batch], threads)]


def decoder_stats(path: Path, crops: np.ndarray, budget: Budget) -> dict[str, float]:
    """Median decode time [ms] of each decoder on one batch-1 output of the model."""
    estimator = PoseEstimator(path)
    output = estimator.run(crops[:1])
    return {decoder: float(np.median(time_calls(partial(decode_output, output, estimator.metadata, decoder),
                                                budget.warmup, budget.iterations[1])))
            for decoder in DECODERS}


def bench_network(name: str, budget: Budget, thread_counts: Sequence[int], bandwidth: dict[int, float],
                  peaks: dict[tuple[int, bool], float], crops: np.ndarray, work: Path) -> dict[str, Any]:
    """Every record of one network, plus its size, node-time shares and decoder times.

    int8 is calibrated on the even crops; every variant's argmax and pose
    agreement with fp32 are measured on the odd ones, which calibration never saw.
    """
    network = NETWORKS[name]
    calibration, held_out = crops[::2], crops[1::2]
    model, metadata, paths = export_variants(name, network, calibration, work)
    macs = count_macs(model, network.config.input_size)
    fp32_output = OnnxEngine(paths["fp32"])(held_out)
    sizes = {variant: weight_bytes(path) for variant, path in paths.items()}
    sizes["torch-eager"] = sum(t.numel() * t.element_size() for t in [*model.parameters(), *model.buffers()])
    agreement = {v: compare(paths[v], OnnxEngine(paths[v])(held_out), fp32_output, metadata) for v in QUANTISED}
    records = []
    for threads in thread_counts:
        for variant in [*paths, "torch-eager"]:
            if variant == "torch-eager":
                rows, shares = torch_stats(model, metadata, crops, threads, budget), {}
            else:
                rows = runtime_stats(paths[variant], threads, budget)
                shares = node_shares(paths[variant], crops[:1], threads, budget.profile_runs, work)
            floor_ms = sizes[variant] / (bandwidth[threads] * 1e9) * 1e3
            compute_floor_ms = macs / (peaks[(threads, variant == "int8-static")] * 1e9) * 1e3
            for row in rows:
                record = {"variant": variant, "network": name, **row, "floor_ms": floor_ms,
                          "x_floor": row["median_ms"] / floor_ms, "weight_mb": sizes[variant] / 1e6,
                          "compute_floor_ms": compute_floor_ms * row["batch"],
                          "x_compute_floor": row["median_ms"] / (compute_floor_ms * row["batch"])}
                if variant in QUANTISED:
                    record["argmax_agreement"] = agreement[variant].argmax_agreement
                    record["pose_agreement"] = agreement[variant].pose_agreement
                if row["batch"] == 1 and row["stage"] == "inference":
                    record.update(shares)
                records.append(record)
    return {
        "records": records,
        "summary": {"network": name, "parameters": count_parameters(model), "macs_per_crop": macs,
                    "output_layer_parameters": sum(p.numel() for p in model.head.parameters()),
                    "decode_ms": decoder_stats(paths["fp32"], crops, budget),
                    "agreement_crops": len(held_out), "calibration_crops": len(calibration)},
    }


def _fmt(value: float | None, digits: int = 2) -> str:
    return "" if value is None else f"{value:.{digits}f}"


def summary_table(records: list[dict[str, Any]]) -> str:
    """Batch 1, 1 thread, inference: each variant against both floors and fp32 (the issue's targets)."""
    rows = [r for r in records if r["batch"] == 1 and r["threads"] == 1 and r["stage"] == "inference"]
    fp32 = {r["network"]: r["median_ms"] for r in rows if r["variant"] == "fp32"}
    return markdown_table(
        ["network", "variant", "median ms", "x memory floor", "compute floor ms", "x compute floor", "fp32 / this",
         "argmax agr.", "pose agr.", "conv share", "output-layer share"],
        [[r["network"], r["variant"], _fmt(r["median_ms"]), _fmt(r["x_floor"], 1), _fmt(r["compute_floor_ms"]),
          _fmt(r["x_compute_floor"], 1), _fmt(fp32[r["network"]] / r["median_ms"], 1),
          _fmt(r.get("argmax_agreement"), 3), _fmt(r.get("pose_agreement"), 3), _fmt(r.get("conv_share"), 2),
          _fmt(r.get("output_layer_share"), 2)]
         for r in rows])


def render_markdown(records: list[dict[str, Any]], summaries: list[dict[str, Any]], bandwidth: dict[int, float],
                    peaks: dict[tuple[int, bool], float], machine_text: str) -> str:
    """Batch-1 summary, the full latency table, then per-network size and decoder tables."""
    rows = [[r["network"], r["variant"], r["threads"], r["batch"], r["stage"], _fmt(r["median_ms"]),
             _fmt(r["p90_ms"]), _fmt(r["p99_ms"]), _fmt(r["crops_per_s"], 0), _fmt(r["floor_ms"], 3),
             _fmt(r["x_floor"], 1), _fmt(r["compute_floor_ms"]), _fmt(r.get("argmax_agreement"), 3),
             _fmt(r.get("pose_agreement"), 3), _fmt(r.get("conv_share"), 2), _fmt(r.get("output_layer_share"), 2)]
            for r in records]
    latency = markdown_table(["network", "variant", "threads", "batch", "stage", "median ms", "p90 ms", "p99 ms",
                              "crops/s", "floor ms", "x floor", "compute floor ms", "argmax agr.", "pose agr.",
                              "conv share", "output-layer share"], rows)
    fp32_inference = {(r["network"], r["threads"]): r["median_ms"] for r in records
                      if r["variant"] == "fp32" and r["stage"] == "inference" and r["batch"] == 1}
    all_threads = max(bandwidth)
    sizes = markdown_table(
        ["network", "parameters", "output-layer parameters", "MMACs/crop", "argmax decode ms", "refined decode ms",
         f"refined / fp32 inference (b1, {all_threads} threads)"],
        [[s["network"], s["parameters"], s["output_layer_parameters"], _fmt(s["macs_per_crop"] / 1e6, 0),
          _fmt(s["decode_ms"]["argmax"], 3), _fmt(s["decode_ms"]["refined"], 3),
          _fmt(s["decode_ms"]["refined"] / fp32_inference[(s["network"], all_threads)], 3)] for s in summaries])
    bandwidths = ", ".join(f"{t} thread(s): {gb:.1f} GB/s" for t, gb in bandwidth.items())
    gemm = ", ".join(f"{t} thread(s): fp32 {peaks[(t, False)]:.0f}, uint8 x int8 {peaks[(t, True)]:.0f} GMAC/s"
                     for t in bandwidth)
    floors = ("Floors: memory = weight bytes / read bandwidth; compute = MACs per crop x batch / GEMM peak "
              "(int8 peak for int8-static, fp32 peak otherwise).")
    return "\n\n".join([machine_text, f"Read bandwidth: {bandwidths}", f"GEMM peak: {gemm}", floors,
                        "Batch 1, 1 thread, inference:", summary_table(records), "All runs:", latency, sizes])


def run(networks: Sequence[str], quick: bool, out_dir: Path, name: str = "latency") -> dict[str, Any]:
    """Measure every network; write ``<name>.json`` and ``<name>.md`` into ``out_dir``; return the payload."""
    budget = QUICK if quick else FULL
    thread_counts = sorted({1, os.cpu_count() or 1})
    bandwidth = {t: read_bandwidth_gb_s(t, budget.bandwidth_mb, budget.bandwidth_repeats) for t in thread_counts}
    peaks = {(t, integer): gemm_peak_gmac_s(t, integer, budget.peak_repeats)
             for t in thread_counts for integer in (False, True)}
    with tempfile.TemporaryDirectory() as folder:
        work = Path(folder)
        sizes = {NETWORKS[n].config.input_size for n in networks}
        crops = {size: rendered_crops(work / str(size), budget.render_per_object, size) for size in sizes}
        results = [bench_network(n, budget, thread_counts, bandwidth, peaks, crops[NETWORKS[n].config.input_size],
                                 work) for n in networks]
    records = [record for result in results for record in result["records"]]
    summaries = [result["summary"] for result in results]
    description = machine()
    markdown = render_markdown(records, summaries, bandwidth, peaks, machine_line(description))
    payload = {"bandwidth_gb_s": {str(t): gb for t, gb in bandwidth.items()},
               "gemm_peak_gmac_s": {f"{t} {'int8' if int8 else 'fp32'}": gmac for (t, int8), gmac in peaks.items()},
               "networks": summaries,
               "records": records, "quick": quick}
    write_results(out_dir, name, payload, markdown)
    print(markdown)
    return payload


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="few iterations: a smoke run, not a measurement")
    parser.add_argument("--out", type=Path, default=Path("bench/results"), help="folder for <name>.json/.md")
    parser.add_argument("--name", default="latency", help="results file name (default: latency)")
    parser.add_argument("--networks", nargs="+", choices=sorted(NETWORKS), default=["paper", "light", "small"])
    args = parser.parse_args(argv)
    return run(args.networks, args.quick, args.out, args.name)


if __name__ == "__main__":
    run_command("bench.latency", main)
