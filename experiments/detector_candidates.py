"""Detector files side by side on the validation bins, rendered and path traced: which one to ship (issue 61).

    OMP_NUM_THREADS=1 python -m experiments.detector_candidates --split runs/shipped_detector2/validation
        --path-traced runs/pt/validation --detector NAME=FILE.onnx [--detector ...] [--poses] [--name NAME]

Each detector at its file's score threshold: COCO AP and AP50 (as the BOP toolkit scores 2-D detection), recall at
IoU 0.5 of parts at least 30 % and 90 % visible and boxes per instance (``experiments.empty_frames.bin_scores``),
with ``--poses`` also the shipped pose models' MSSD from its boxes (every instance scored, a missed one wrong), on
each split given: validation splits only (the bin of seed 4000 and ``popcode-train path-trace`` of it). Writes
``bench/results/NAME.{json,md}`` (``--name``, ``detector-candidates`` by default: a later comparison beside an
earlier one).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path
from typing import Any

from popcode_runtime.inference.detector import Detector
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

from .empty_frames import bin_scores


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--split", type=Path, required=True, help="the rendered validation bin split")
    parser.add_argument("--path-traced", type=Path, help="the same split path traced")
    parser.add_argument("--detector", action="append", required=True, metavar="NAME=FILE",
                        help="a candidate, named (repeat)")
    parser.add_argument("--poses", action="store_true", help="also the shipped pose models' MSSD from the boxes")
    parser.add_argument("--work", type=Path, default=Path("runs/detector_candidates"))
    parser.add_argument("--name", default="detector-candidates", help="the results' name in bench/results")
    args = parser.parse_args()
    splits = {"rendered": args.split, **({"path-traced": args.path_traced} if args.path_traced else {})}
    rows = []
    for item in args.detector:
        name, _, path = item.partition("=")
        for split_name, split_dir in splits.items():
            work = args.work / name / split_name
            work.mkdir(parents=True, exist_ok=True)
            rows.append({"detector": name, "file": path, "split": split_name,
                         **bin_scores(Detector(path, threads=1), split_dir, work, args.poses)})
    payload = {"command": shlex.join(["python", "-m", "experiments.detector_candidates", *sys.argv[1:]]),
               "threads": os.environ.get("OMP_NUM_THREADS"), "rows": rows}
    write_results(RESULTS, args.name, payload, _markdown(payload))


def _markdown(payload: dict[str, Any]) -> str:
    poses = "MSSD" in payload["rows"][0]
    table = markdown_table(
        ["detector", "split", "AP", "AP50", "recall ≥ 30 % visible", "recall ≥ 90 % visible", "boxes / instance",
         *(["MSSD from its boxes"] if poses else [])],
        [[row["detector"], row["split"], *(f"{100 * row[k]:.1f}" for k in ("AP", "AP50", "recall_30", "recall_90")),
          f"{row['boxes_per_instance']:.2f}", *([f"{100 * row['MSSD']:.1f}"] if poses else [])]
         for row in payload["rows"]])
    return "\n\n".join([
        "# Detector candidates on the validation bins (`python -m experiments.detector_candidates`)",
        f"Command: `{payload['command']}` (OMP_NUM_THREADS={payload['threads']}); each detector at its file's score "
        "threshold; validation splits only (the bin of seed 4000, industrial camera, and its path-traced copy).",
        table, machine_line(machine())])


if __name__ == "__main__":
    run_command("experiments.detector_candidates", main)
