"""Does a detector pretrained on many generated parts give the demo's detector a head start? AP on the cluttered
validation split of the demo's detector (its recipe, scenes and minutes) from random weights and from that start.

    python -m experiments.detector_start --parts DIR --parts-scenes DIR [DIR ...] [--work runs/detector_start]
        [--pretrain-epochs 60] [--demo-scenes DIR] [--minutes 2.5] [--validation-scenes 60] [--seed 0] [--ship]

The start: ``DEMO_DETECTOR`` trained for ``--pretrain-epochs`` on bin scenes of generated parts (each part its own
class; rendered by ``popcode-train render --objects`` from the parts ``popcode-train pretrain`` generates), all of
its weights but the classification logits, written as a detector start (``detection.start``) with its card
(``WORK/detector-start.pt``; ``--ship`` copies it to ``models/``, where ``detector.init = "auto"`` finds it). Then
the demo's detector (``--demo-scenes``: the demo's training scenes of the built-in parts, seed 3000, industrial
camera; ``--minutes``: its budget, epochs fitted) twice, from random weights (``detector.init = "none"``) and from
the start, each scored on the validation bin split (seed 4000, industrial) with the BOP toolkit's COCO AP. Run it
alone: the epochs are fitted to this machine's speed. ``--work`` keeps runs: a rerun scores what is there. Results:
``bench/results/detector-start.{json,md}``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import torch

from experiments.shipped_detector import render_scenes, run_training, score_cells, validation_scores
from popcode_runtime.base.files import copy_file_atomic
from popcode_runtime.bop.split import split_images
from popcode_runtime.inference.benchmark import machine_description
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.demo.sizes import DEMO_DETECTOR
from popcode_trainer.detection.export import export_detector
from popcode_trainer.detection.loop import train_detector
from popcode_trainer.detection.network import build_detector
from popcode_trainer.detection.start import shipped_detector_start, write_detector_start
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.train.checkpoint import git_revision, load
from tools.command import run_command
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

VALIDATION_SEED = 4000


def pretrained_start(work: Path, parts: Path, scenes: Sequence[Path], epochs: int) -> tuple[Path, dict[str, Any]]:
    """Train (or resume) the detector of every generated part from random weights and write its start with a card;
    the start file and the card."""
    obj_ids = sorted(load_models_info(parts))
    folder = work / "pretrain"
    run = train_detector(scenes, obj_ids, folder, replace(DEMO_DETECTOR, epochs=epochs, init="none"))
    model = build_detector(run.config, len(obj_ids))
    model.load_state_dict(load(run.checkpoint)["model"])
    card = {"parts": len(obj_ids), "scenes": sum(len(split_images(split)) for split in scenes), **run_training(folder),
            "command": "python -m experiments.detector_start", "commit": git_revision(),
            "date": time.strftime("%Y-%m-%d"), "machine": {**machine_description(), "torch": str(torch.__version__)}}
    return write_detector_start(model, run.config, work / "detector-start.pt", card), card


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--parts", type=Path, required=True, help="models folder of the generated parts")
    parser.add_argument("--parts-scenes", type=Path, nargs="+", required=True, help="bin scenes of generated parts")
    parser.add_argument("--work", type=Path, default=Path("runs/detector_start"))
    parser.add_argument("--pretrain-epochs", type=int, default=60)
    parser.add_argument("--demo-scenes", type=Path, required=True, help="the demo's training scenes")
    parser.add_argument("--minutes", type=float, default=2.5, help="the demo detector's budget")
    parser.add_argument("--validation-scenes", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0, help="the demo detectors' seed (weights, order, held out)")
    parser.add_argument("--ship", action="store_true", help="copy the start into models/ (the shipped start)")
    parser.add_argument("--name", default="detector-start")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    validation = render_scenes(args.work / "validation", args.validation_scenes, VALIDATION_SEED, "industrial")
    start, pretraining = pretrained_start(args.work, args.parts, args.parts_scenes, args.pretrain_epochs)
    if args.ship:
        copy_file_atomic(start, shipped_detector_start(DEMO_DETECTOR))
    records: list[dict[str, Any]] = []
    for arm, init in (("random weights", "none"), ("pretrained start", str(start))):
        folder = args.work / (arm.replace(" ", "_") + (f"_seed{args.seed}" if args.seed else ""))
        run = train_detector([args.demo_scenes], [1, 2, 3, 4, 5, 6], folder,
                             replace(DEMO_DETECTOR, init=init, seed=args.seed), seconds=60.0 * args.minutes)
        detector = export_detector(run.checkpoint, folder / "detector.onnx")
        records.append({"arm": arm, **run_training(folder), **validation_scores(detector, validation)})
    rows = [[r["arm"], r["epochs"], f"{r['training_s'] / 60:.1f}",
             f"{r['best_val_loss']:.3f} / {r['last_val_loss']:.3f}", *score_cells(r)] for r in records]
    markdown = "\n".join([
        f"# {args.name}: the demo's detector from random weights and from a start pretrained on generated parts",
        "",
        "`" + " ".join(["python -m experiments.detector_start", *(sys.argv[1:] if argv is None else argv)]) + "`",
        "",
        f"Start: {pretraining['parts']} generated parts, {pretraining['epochs']} epochs, "
        f"{pretraining['training_s'] / 60:.1f} training minutes, validation loss best / last "
        f"{pretraining['best_val_loss']:.3f} / {pretraining['last_val_loss']:.3f}. Demo detectors' seed "
        f"{args.seed}. Validation bin split: seed "
        f"{VALIDATION_SEED}, {args.validation_scenes} scenes, industrial camera; COCO AP on amodal boxes.",
        "",
        markdown_table(["demo detector", "epochs", "training min", "validation loss best / last", "AP", "AP50",
                        "AP75", "recall ≥ 30 % visible"], rows),
        "",
        machine_line(machine()),
    ])
    write_results(args.out, args.name, {"pretraining": pretraining, "runs": records,
                                        "arguments": {k: str(v) for k, v in vars(args).items()}}, markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    run_command("experiments.detector_start", main)
