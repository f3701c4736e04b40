"""What a ROS 2 bag costs ``popcode bag`` beside the frame pipeline alone: reading and decoding each frame and its
camera from the bag, writing its ``Detection3DArray`` and ``PoseArray`` (and, asked, the Foxglove file).

    python -m bench.bag_overhead [--frames 300] [--parts 10] [--threads 1] [--repeats 3]

A bag of ``--frames`` copies of the sample bin frame (720 x 540, mono8, ten parts) with its ``CameraInfo`` is
written by rosbags in each storage (SQLite3, MCAP). Timed, per repeat and in alternating order: the shipped
detector and pose models (``FramePoseEstimator``, its ``--parts`` best boxes) on the frames already in memory,
then the same through ``popcode bag``'s own reader and writer (models loaded before the clock starts), without and
with ``--foxglove``. The goal (issue 64): at most 10 % more time than the pipeline alone. Writes
``bench/results/bag-overhead.{json,md}``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from contextlib import nullcontext
from importlib.metadata import version
from pathlib import Path

import cv2
import numpy as np

from popcode_runtime import Detector, FramePoseEstimator, PoseEstimator
from popcode_runtime.ros.bag_input import BagFrames, Topics, open_bag
from popcode_runtime.ros.bag_output import BagOutput
from popcode_runtime.ros.foxglove_scene import FoxgloveOutput
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import MODELS_DIR, RESULTS, SHIPPED_DETECTOR, SHIPPED_MODELS
from tools.report import machine, machine_line, write_results
from tools.ros_bags import (
    IMAGE_TOPIC,
    INFO_TOPIC,
    PERIOD_NS,
    SAMPLE_BIN_K,
    START_NS,
    camera_info,
    image,
    write_bag,
)

BIN = MODELS_DIR / "samples" / "bin.png"


def _recording(folder: Path, frames: int, storage: str) -> Path:
    grey = cv2.imread(str(BIN), cv2.IMREAD_UNCHANGED)
    messages = [m for i in range(frames) for m in (camera_info(START_NS + i * PERIOD_NS, SAMPLE_BIN_K, (720, 540)),
                                                    image(START_NS + i * PERIOD_NS, grey, "mono8"))]
    return write_bag(folder / f"recorded-{storage}", messages, storage)


def _alone(estimator: FramePoseEstimator, frames: int) -> float:
    """Seconds of the pipeline on ``frames`` frames already in memory."""
    grey = cv2.imread(str(BIN), cv2.IMREAD_UNCHANGED)
    started = time.perf_counter()
    for _ in range(frames):
        estimator.estimate(grey, K=SAMPLE_BIN_K)
    return time.perf_counter() - started


def _through_bag(estimator: FramePoseEstimator, objects: dict, bag: Path, out: Path, foxglove: Path | None) -> float:
    """Seconds of ``popcode bag``'s loop: read, estimate, write (and the Foxglove file), the bag put in place."""
    started = time.perf_counter()
    scene = FoxgloveOutput(foxglove, objects) if foxglove else nullcontext(None)
    with open_bag(bag) as reader, BagOutput(out, "mcap", "/popcode/detections", "/popcode/poses", objects) as output, \
            scene as view:
        for frame in BagFrames(reader, Topics(IMAGE_TOPIC, INFO_TOPIC), bag).frames():
            poses = estimator.estimate(frame.image, K=frame.K)
            output.add(frame, poses)
            if view is not None:
                view.add(frame, poses)
        output.finish()
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--parts", type=int, default=10, help="poses a frame (the detector's best boxes)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    estimators = [PoseEstimator(path, threads=args.threads) for path in SHIPPED_MODELS]
    detector = Detector(SHIPPED_DETECTOR, threads=args.threads, max_detections=args.parts)
    estimator = FramePoseEstimator(detector, estimators)
    objects = {obj_id: info for e in estimators for obj_id, info in e.metadata.objects.items()}
    _alone(estimator, 3)  # warm-up
    seconds: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory(prefix="bag-overhead-") as scratch:
        folder = Path(scratch)
        bags = {storage: _recording(folder, args.frames, storage) for storage in ("sqlite3", "mcap")}
        for repeat in range(args.repeats):
            seconds.setdefault("pipeline alone", []).append(_alone(estimator, args.frames))
            for storage, bag in bags.items():
                for foxglove in (False, True):
                    name = f"{storage} bag in, mcap bag out" + (", --foxglove" if foxglove else "")
                    out = folder / f"out-{repeat}-{storage}-{foxglove}"
                    view = folder / f"view-{repeat}-{storage}.mcap" if foxglove else None
                    seconds.setdefault(name, []).append(_through_bag(estimator, objects, bag, out, view))
    alone = float(np.median(seconds["pipeline alone"]))
    rows = [{"path": name, "ms_per_frame": 1000 * float(np.median(values)) / args.frames,
             "overhead": float(np.median(values)) / alone - 1.0, "seconds": values} for name, values in seconds.items()]
    table = markdown_table(["path", "ms a frame (median of repeats)", "more than the pipeline alone"],
                           [[r["path"], f"{r['ms_per_frame']:.1f}", f"{100 * r['overhead']:+.1f} %"] for r in rows])
    versions = {name: version(name) for name in ("rosbags", "foxglove-sdk", "mcap")}
    markdown = "\n\n".join([
        "# popcode bag: what the bag costs beside the frame pipeline",
        f"`python -m bench.bag_overhead --frames {args.frames} --parts {args.parts} --threads {args.threads} "
        f"--repeats {args.repeats}`; the sample bin frame (720 x 540, mono8) in every frame of the bag, the "
        f"shipped detector and pose models on its {args.parts} best boxes; the goal is at most +10 %. The bag's "
        "time includes opening the bags and syncing the output at the end; `--foxglove` also copies each frame's "
        "image into its file.",
        table, machine_line(machine()) + " " + ", ".join(f"{k} {v}" for k, v in versions.items()) + "."])
    write_results(RESULTS, "bag-overhead", {"frames": args.frames, "parts": args.parts, "threads": args.threads,
                                            "versions": versions, "rows": rows}, markdown)
    print(markdown)


if __name__ == "__main__":
    run_command("bench.bag_overhead", main)
