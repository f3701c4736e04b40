"""The whole frame on this CPU: the shipped detector and the shipped pose models on the sample bin frame, from
the camera image to every part's pose, through the runtime's ``FramePoseEstimator``.

    python -m bench.frame_latency [--parts 10] [--iterations 50] [--threads 1 2] [--detector DET.onnx]
        [--name frame-latency]

Per thread count: the detector (resize, network, threshold, NMS), then the pose models on its ``--parts`` best
boxes (crop, network, decoding, translation from the box and the confidence), median and 90th percentile over
the iterations after a warm-up. The sample frame (``models/samples/bin.png``, 720 x 540) holds ten parts.
``--detector`` times a candidate detector instead of the shipped one. Writes ``bench/results/NAME.{json,md}``
(``--name``, ``frame-latency`` by default).
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from popcode_runtime import Detector, FramePoseEstimator, PoseEstimator, read_image
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import MODELS_DIR, RESULTS, SHIPPED_DETECTOR, SHIPPED_MODELS
from tools.report import machine, machine_line, write_results

SAMPLE = MODELS_DIR / "samples" / "samples.json"


def time_frames(threads: int, parts: int, iterations: int, detector: Path = SHIPPED_DETECTOR) -> dict[str, float]:
    """Median and 90th percentile ms of the detector, the poses and the whole frame."""
    sample = json.loads(SAMPLE.read_text())["bin"]
    image = read_image(SAMPLE.parent / sample["image"])
    frames = FramePoseEstimator(Detector(detector, threads=threads, max_detections=parts),
                                [PoseEstimator(path, threads=threads) for path in SHIPPED_MODELS])
    detect, poses, total, found = [], [], [], []
    for index in range(iterations + 3):
        started = time.perf_counter()
        estimated = frames.estimate(image, K=sample["K"])
        took = time.perf_counter() - started
        if index >= 3:  # warm-up
            detect.append(1000 * frames.last_timings.detect_s)
            poses.append(1000 * frames.last_timings.poses_s)
            total.append(1000 * took)
            found.append(len(estimated))
    return {"threads": threads, "parts": float(np.median(found)),
            **{f"{name}_{stat}": float(np.percentile(values, q)) for name, values in
               (("detect_ms", detect), ("poses_ms", poses), ("frame_ms", total)) for stat, q in (("median", 50),
                                                                                                ("p90", 90))}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", type=int, default=10, help="poses a frame (the detector's best boxes)")
    parser.add_argument("--iterations", type=int, default=50)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--detector", type=Path, default=SHIPPED_DETECTOR, help="the detector file to time")
    parser.add_argument("--name", default="frame-latency", help="the results' name in bench/results")
    args = parser.parse_args()
    rows = [time_frames(threads, args.parts, args.iterations, args.detector) for threads in args.threads]
    table = markdown_table(["threads", "parts posed", "detector ms", "poses ms", "frame ms (median)",
                            "frame ms (p90)"],
                           [[str(r["threads"]), f"{r['parts']:.0f}", f"{r['detect_ms_median']:.1f}",
                             f"{r['poses_ms_median']:.1f}", f"{r['frame_ms_median']:.1f}",
                             f"{r['frame_ms_p90']:.1f}"] for r in rows])
    shipped = args.detector == SHIPPED_DETECTOR
    command = shlex.join(["python", "-m", "bench.frame_latency", *sys.argv[1:]])
    which = "the shipped detector and" if shipped else f"the detector `{args.detector}` and the shipped"
    markdown = "\n\n".join([f"# A whole frame: {which} pose models on the sample bin frame",
                            f"`{command}`; median over the iterations after three warm-up calls.", table,
                            machine_line(machine())])
    write_results(RESULTS, args.name, {"detector": str(args.detector), "rows": rows}, markdown)
    print(markdown)


if __name__ == "__main__":
    run_command("bench.frame_latency", main)
