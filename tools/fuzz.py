"""Fuzz ``PoseEstimator.predict`` with random, mostly hostile, arguments: every call must either return
valid rotations or raise ``PopcodeError`` (issue 19). Anything else is counted as unhandled, a call still running
after :data:`CALL_LIMIT_S` (its watchdog) too.

Images of every dtype and shape (NaN, out of range, empty, RGBA), boxes from sub-pixel to 1e300 px,
NaN and inf, camera matrices from physical to absurd, ``top_k``/``obj_ids`` of the wrong type. The
suite runs a short fixed-seed fuzz; this script runs a long one on a real model and records it:

    python -m tools.fuzz --calls 20000
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime import PopcodeError, PoseEstimator
from popcode_trainer.train.deadline import deadline
from tools.command import run_command
from tools.paths import RESULTS, SHIPPED_3_6

MAX_SIDE = 400  # random images stay small: the fuzz is about arguments, not about pixels
CALL_LIMIT_S = 10.0  # a call still running then is a hang (the slowest calls take about half a second)


class CallTimeout(BaseException):
    """Raised by the watchdog in a call that ran past its limit (a ``BaseException``: nothing may catch it)."""


def pick(rng: np.random.Generator, options: Sequence[Any]) -> Any:
    """One of ``options`` (``rng.choice`` would make an array of them, which mixed types cannot be)."""
    return options[int(rng.integers(len(options)))]


def _image(rng: np.random.Generator) -> Any:
    height, width = (int(v) for v in rng.integers(1, MAX_SIDE, size=2))
    kind = rng.integers(16)
    if kind < 8:
        return rng.integers(0, 256, size=(height, width), dtype=np.uint8)
    if kind in (8, 9):
        return rng.integers(0, 65536, size=(height, width, 3), dtype=np.uint16)
    if kind == 10:
        return rng.random((height, width), dtype=np.float32)
    if kind == 11:
        image = rng.random((height, width)).astype(np.float64)
        image[rng.integers(height), rng.integers(width)] = pick(rng, [np.nan, np.inf, -1.0, 2.0])
        return image
    if kind == 12:
        return rng.integers(0, 256, size=(height, width, int(pick(rng, [1, 2, 4]))), dtype=np.uint8)
    if kind == 13:
        return np.zeros((int(rng.integers(0, 2)), width), np.uint8)
    if kind == 14:
        return rng.integers(0, 256, size=(height, width)).astype(pick(rng, [np.int32, np.int8, np.bool_]))
    if rng.random() < 0.5:
        return rng.integers(0, 256, size=width, dtype=np.uint8)
    return pick(rng, [[[0, 1], [2, 3]], None])


def _number(rng: np.random.Generator, scale: float) -> Any:
    kind = rng.integers(40)
    if kind == 0:
        return float(pick(rng, [np.nan, np.inf, -np.inf]))
    if kind == 1:
        return float(pick(rng, [1e-9, 1e5, 1e9, 1e300, -1e300]))
    if kind == 2:
        return pick(rng, ["12", None, True, [1.0]])
    return float(rng.uniform(-0.2, 1.2) * scale)


def _box(rng: np.random.Generator, shape: tuple[int, ...]) -> Any:
    height, width = (shape[0], shape[1]) if len(shape) >= 2 else (MAX_SIDE, MAX_SIDE)
    if rng.random() < 0.05:
        return pick(rng, ["0,0,10,10", None, [1.0, 2.0, 3.0], [1, 2, 3, 4, 5]])
    if rng.random() < 0.9:
        w, h = rng.uniform(2, max(3, width), size=1)[0], rng.uniform(2, max(3, height), size=1)[0]
        return [float(rng.uniform(-w / 2, width)), float(rng.uniform(-h / 2, height)), float(w), float(h)]
    return [_number(rng, width), _number(rng, height), _number(rng, width), _number(rng, height)]


def _camera(rng: np.random.Generator) -> Any:
    kind = rng.integers(10)
    if kind < 4:
        return None
    if kind < 8:
        return [float(rng.uniform(100, 3000)), float(rng.uniform(100, 3000)), float(rng.uniform(0, 800)),
                float(rng.uniform(0, 600))]
    if kind == 8:
        return [_number(rng, 1000.0) for _ in range(int(pick(rng, [3, 4, 9])))]
    return pick(rng, ["500,500,320,240", [[1.0, 2.0], [3.0]], np.eye(2)])


def random_call(rng: np.random.Generator, obj_ids: Sequence[int]) -> dict[str, Any]:
    """Keyword arguments for one ``predict`` call, each argument hostile with some probability."""
    image = _image(rng)
    count = int(pick(rng, [0, 1, 1, 2, 3, 8, 40]))
    boxes = [_box(rng, np.shape(image)) for _ in range(count)]
    if rng.random() < 0.03:
        boxes = pick(rng, [None, "boxes", 5])
    call = {"image": image, "boxes": boxes, "K": _camera(rng), "translation": bool(rng.random() < 0.15),
            "return_code": bool(rng.random() < 0.2),
            "top_k": pick(rng, [1] * 12 + [2] * 4 + [3] * 4 + [0, -1, "2", 2.5, None, 1000])}
    if rng.random() < 0.3:
        call["obj_ids"] = ([int(pick(rng, obj_ids))] * count if rng.random() < 0.8
                          else pick(rng, [[3.7], [99] * count, "7", [None] * count]))
    return call


@dataclass
class FuzzReport:
    """What the calls did: returned rotations, refused with ``PopcodeError``, or anything else (unhandled: another
    exception, or a hang past the watchdog's limit)."""

    calls: int = 0
    returned: int = 0
    refused: int = 0
    invalid_rotations: int = 0
    unhandled: list[str] = field(default_factory=list)
    slowest_s: float = 0.0
    refusals: Counter = field(default_factory=Counter)

    def to_dict(self) -> dict[str, Any]:
        return {"calls": self.calls, "returned": self.returned, "refused": self.refused,
                "invalid_rotations": self.invalid_rotations, "unhandled": len(self.unhandled),
                "unhandled_examples": self.unhandled[:10], "slowest_call_s": self.slowest_s,
                "most_common_refusals": self.refusals.most_common(12)}


def _valid(prediction: Any) -> bool:
    R = prediction.R_m2c
    ok = np.isfinite(R).all() and np.allclose(R @ R.T, np.eye(3), atol=1e-5) and abs(np.linalg.det(R) - 1) < 1e-5
    return bool(ok and (prediction.t_m2c_mm is None or np.isfinite(prediction.t_m2c_mm).all()))


def fuzz(estimator: PoseEstimator, calls: int, seed: int = 0, limit_s: float = CALL_LIMIT_S) -> FuzzReport:
    """``calls`` random ``predict`` calls with a fixed seed, each under a watchdog of ``limit_s``."""
    rng = np.random.default_rng(seed)
    obj_ids = sorted(estimator.metadata.objects)
    report = FuzzReport()
    for _ in range(calls):
        arguments = random_call(rng, obj_ids)
        started = time.perf_counter()
        try:
            with deadline(limit_s, CallTimeout(f"still running after {limit_s:g} s")):
                predictions = estimator.predict(**arguments)
        except PopcodeError as error:
            report.refused += 1
            report.refusals[" ".join(str(error).split()[:4])] += 1
        except CallTimeout as error:
            report.unhandled.append(f"hang: {error}")
        except Exception as error:  # what the fuzz is looking for
            report.unhandled.append(f"{type(error).__name__}: {str(error)[:200]}")
        else:
            report.returned += 1
            report.invalid_rotations += sum(not _valid(p) for p in predictions)
        report.slowest_s = max(report.slowest_s, time.perf_counter() - started)
        report.calls += 1
    return report


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", type=Path, default=SHIPPED_3_6)
    parser.add_argument("--calls", type=int, default=20000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    from tools.report import write_results  # torch, for the machine record; the fuzz itself needs no torch

    started = time.perf_counter()
    report = fuzz(PoseEstimator(args.model, threads=args.threads), args.calls, args.seed)
    seconds = time.perf_counter() - started
    result = {**report.to_dict(), "model": args.model.name, "seed": args.seed, "seconds": seconds,
              "call_limit_s": CALL_LIMIT_S}
    lines = [f"# Fuzz of PoseEstimator.predict ({args.model.name}, seed {args.seed})", "",
             "| calls | returned | refused (PopcodeError) | unhandled | invalid rotations | slowest call s | total s |",
             "|---:|---:|---:|---:|---:|---:|---:|",
             f"| {report.calls} | {report.returned} | {report.refused} | {len(report.unhandled)} | "
             f"{report.invalid_rotations} | {report.slowest_s:.2f} | {seconds:.0f} |", "",
             f"Each call ran under a {CALL_LIMIT_S:.0f} s watchdog (one still running then counts as unhandled).", "",
             "Most common refusals: " + "; ".join(f"{text}... ({n})" for text, n in report.refusals.most_common(8))]
    json_path, _ = write_results(args.out, "fuzz", {"fuzz": result}, "\n".join(lines))
    print("\n".join(lines))
    print(f"wrote {json_path}")
    return 1 if report.unhandled or report.invalid_rotations else 0


if __name__ == "__main__":
    run_command("tools.fuzz", main)
