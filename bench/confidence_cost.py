"""What the calibrated confidence costs at run time: ``predict`` with and without the model's calibrator.

    python -m bench.confidence_cost [--model M --obj-id ID ...] [--iterations 300] [--threads 1]

Each shipped model (one of its objects per call) runs ``PoseEstimator.predict`` on a 720 x 540 frame
at batch 1 and 8, once as shipped (confidence computed from the code) and once with the calibrator
dropped from its metadata (confidence None), alternating, median of ``--iterations`` calls.
Results: ``bench/results/confidence-cost.{json,md}``.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from popcode_runtime import PoseEstimator
from popcode_runtime.inference.benchmark import time_calls
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import RESULTS, SHIPPED_1_2, SHIPPED_3_6
from tools.report import write_results

DEFAULT_CASES = ((SHIPPED_1_2, 1), (SHIPPED_3_6, 4))
BATCHES = (1, 8)


def median_ms(estimator: PoseEstimator, image: np.ndarray, obj_id: int, batch: int, iterations: int) -> float:
    boxes = [[100.0 + 60.0 * i, 120.0, 90.0, 80.0] for i in range(batch)]
    times_ms = time_calls(lambda: estimator.predict(image, boxes, obj_ids=[obj_id] * batch),
                          warmup=max(5, iterations // 10), iterations=iterations)
    return float(np.median(times_ms))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", type=Path, action="append", help="model file (repeat; default: the shipped)")
    parser.add_argument("--obj-id", type=int, action="append", help="the object of each --model")
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    cases = list(zip(args.model, args.obj_id, strict=True)) if args.model else list(DEFAULT_CASES)
    image = np.random.default_rng(0).random((540, 720)).astype(np.float32)
    rows = []
    for path, obj_id in cases:
        estimator = PoseEstimator(path, threads=args.threads)
        if estimator.metadata.confidence is None:
            raise SystemExit(f"{path} has no confidence calibrator to measure")
        shipped = estimator.metadata
        for batch in BATCHES:
            timings = {}
            for label, metadata in (("with", shipped), ("without", dataclasses.replace(shipped, confidence=None))):
                estimator.metadata = metadata
                timings[label] = median_ms(estimator, image, obj_id, batch, args.iterations)
            rows.append({"model": path.name, "obj_id": obj_id, "batch": batch, "with_ms": timings["with"],
                         "without_ms": timings["without"],
                         "per_crop_ms": (timings["with"] - timings["without"]) / batch})
    lines = ["# Cost of the calibrated confidence in `PoseEstimator.predict`", "",
             f"Median of {args.iterations} calls, {args.threads} thread(s), 720 x 540 frame; `python -m "
             "bench.confidence_cost`.", "",
             markdown_table(["model", "object", "batch", "with confidence ms", "without ms", "added ms per crop"],
                            [[r["model"], r["obj_id"], r["batch"], f"{r['with_ms']:.2f}", f"{r['without_ms']:.2f}",
                              f"{r['per_crop_ms']:.2f}"] for r in rows])]
    json_path, _ = write_results(args.out, "confidence-cost", {"rows": rows}, "\n".join(lines))
    print("\n".join(lines))
    print(f"wrote {json_path}")
    return 0


if __name__ == "__main__":
    run_command("bench.confidence_cost", main)
