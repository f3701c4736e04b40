"""Detector recipes against each other: AP on a cluttered *validation* split against training time and the
runtime's latency, each recipe trained for the same minutes on one core (two recipes can run side by side on a
2-core machine without skewing each other).

    python -m experiments.detector_choices train RECIPE --train DIR --val DIR --minutes M [--work DIR]
    python -m experiments.detector_choices report --val DIR [--work DIR] [--name NAME]

``train`` runs ``popcode-train train-detector`` with the recipe's settings (one thread) into ``WORK/RECIPE``
(rerun to resume), then detects on the validation split with ``popcode detect``; ``report`` scores every
recipe's detections (COCO AP as the BOP toolkit) and times its detector on the validation frames (one thread,
median of the frames after a warm-up), writing ``bench/results/detector-<name>.{json,md}``. The validation split
is the project's cluttered validation seed (4000, ``popcode-train render --scenes N --seed 4000``); no test
split is read.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.bop.detections import read_detections
from popcode_runtime.bop.split import split_images
from popcode_runtime.geometry.crop import read_image_file
from popcode_runtime.inference.detector import Detector
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.detection_scores import detection_scores
from tools.command import run_command
from tools.report import machine_line, write_results

NARROW = {"widths": [16, 32, 48, 64, 96], "fpn_channels": 64}
SMALL = {**NARROW, "input_width": 256, "input_height": 192}
RECIPES: dict[str, dict[str, object]] = {  # each spelt out: the config's defaults are the winner's
    "384x288-head2": {**NARROW, "input_width": 384, "input_height": 288, "head_convs": 2},
    "256x192-head2": {**SMALL, "head_convs": 2},
    "256x192-head1": {**SMALL, "head_convs": 1},
    "256x192-head1-lr5e-3": {**SMALL, "head_convs": 1, "lr": 5e-3},
    "256x192-head1-wide": {**SMALL, "head_convs": 1, "widths": [24, 48, 64, 96, 128]},
}
TIMED_FRAMES = 20


def _settings(recipe: str) -> list[str]:
    return [item for key, value in RECIPES[recipe].items() for item in ("--set", f"detector.{key}={value}")]


def train(recipe: str, train_split: Path, val_split: Path, minutes: float, work: Path) -> None:
    run = work / recipe
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    started = time.perf_counter()
    subprocess.run([sys.executable, "-m", "popcode_trainer.cli", "train-detector", "--split", str(train_split),
                    "--out", str(run), "--minutes", str(minutes), "--quiet", *_settings(recipe)],
                   check=True, env=environment)
    write_bytes_atomic(run / "wall_seconds.txt", f"{time.perf_counter() - started:.1f}\n".encode())
    subprocess.run([sys.executable, "-m", "popcode_runtime.commands.cli", "detect", str(run / "detector.onnx"),
                    "--split", str(val_split), "--out", str(run / "val_detections.json"), "--overwrite", "--quiet",
                    "--threads", "1"], check=True, env=environment)


def _latency_ms(detector_path: Path, val_split: Path) -> float:
    detector = Detector(detector_path, threads=1)
    frames = [read_image_file(image.path) for image in list(split_images(val_split).values())[:TIMED_FRAMES]]
    detector.detect(frames[0])
    seconds = []
    for frame in frames:
        detector.detect(frame)
        seconds.append(detector.last_seconds)
    return 1000.0 * float(np.median(seconds))


def report(val_split: Path, work: Path, name: str) -> None:
    rows, payload = [], {}
    for recipe in RECIPES:
        run = work / recipe
        if not (run / "val_detections.json").is_file():
            continue
        scores = detection_scores(val_split, read_detections(run / "val_detections.json"))
        epochs = len((run / "metrics.csv").read_text().splitlines()) - 1
        latency = _latency_ms(run / "detector.onnx", val_split)
        payload[recipe] = {"settings": RECIPES[recipe], "epochs": epochs, "latency_ms_1_thread": latency,
                           "wall_seconds": float((run / "wall_seconds.txt").read_text()),
                           "scores": scores.to_dict()}
        coco = scores.coco
        rows.append([recipe, str(epochs), f"{payload[recipe]['wall_seconds'] / 60:.1f}",
                     *(f"{100 * (coco[k] or 0):.1f}" for k in ("AP", "AP50", "AP75", "AR100")),
                     f"{100 * scores.recall_goal.recall:.1f}", f"{latency:.1f}"])
    table = markdown_table(["recipe", "epochs", "min", "AP", "AP50", "AP75", "AR100", "recall ≥30 % vis.",
                            "ms/frame (1 thread)"], rows)
    from tools.report import machine

    markdown = "\n\n".join([f"# Detector recipes on a cluttered validation split ({val_split})",
                            "Each recipe trained for the same minutes on one core (`python -m "
                            "experiments.detector_choices train ...`), scored by `popcode-train "
                            "evaluate-detections`'s scorer (COCO AP on amodal boxes, as the BOP toolkit).",
                            table, machine_line(machine())])
    write_results(Path("bench/results"), f"detector-{name}", {"recipes": payload}, markdown)
    print(markdown)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    one = commands.add_parser("train")
    one.add_argument("recipe", choices=list(RECIPES))
    one.add_argument("--train", type=Path, required=True)
    one.add_argument("--val", type=Path, required=True)
    one.add_argument("--minutes", type=float, required=True)
    one.add_argument("--work", type=Path, default=Path("runs/detector_choices"))
    summary = commands.add_parser("report")
    summary.add_argument("--val", type=Path, required=True)
    summary.add_argument("--work", type=Path, default=Path("runs/detector_choices"))
    summary.add_argument("--name", default="recipes")
    args = parser.parse_args()
    if args.command == "train":
        train(args.recipe, args.train, args.val, args.minutes, args.work)
    else:
        report(args.val, args.work, args.name)


if __name__ == "__main__":
    run_command("experiments.detector_choices", main)
