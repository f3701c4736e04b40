"""What limits the quick demo's detector: its minutes or its scenes. AP on the cluttered validation split of
detectors trained as the demo trains one (its recipe, its training scenes' seed and camera), for several time
budgets and numbers of training scenes.

    python -m experiments.demo_detector_curve [--work runs/demo_detector_curve] [--runs 150:2.5 150:10 600:10]
        [--init none|auto|START.pt] [--validation-scenes 60] [--name demo-detector-curve]

Each ``SCENES:MINUTES`` run renders (once) that many training scenes as the demo does (seed 3000, industrial camera)
and trains ``popcode_trainer.demo.sizes.DEMO_DETECTOR`` on them from the first weights ``--init`` names
(``detector.init``; by default random weights, as the demo's detector trained before it took the shipped detector
start) with its epochs fitted to the minutes, as ``train_demo_detector`` does; the quick demo is ``150:2.5``. Every
detector is scored on the validation bin split (seed 4000, industrial, as ``experiments.shipped_detector``'s) with
the BOP toolkit's COCO AP. Run it alone: the epochs are fitted to this machine's speed. ``--work`` keeps scenes and
runs: a rerun scores what is there. Results: ``bench/results/<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from experiments.shipped_detector import render_scenes, run_training, score_cells, validation_scores
from popcode_trainer.demo.sizes import DEMO_DETECTOR
from popcode_trainer.detection.export import export_detector
from popcode_trainer.detection.loop import train_detector
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

TRAIN_SEED, VALIDATION_SEED = 3000, 4000  # the demo's training scenes; the project's cluttered validation seed


def parse_run(text: str) -> tuple[int, float]:
    scenes, _, minutes = text.partition(":")
    try:
        return int(scenes), float(minutes)
    except ValueError:
        raise SystemExit(f"--runs {text!r}: give SCENES:MINUTES, e.g. 150:2.5") from None


def trained_detector(work: Path, scenes: int, minutes: float, init: str) -> tuple[Path, dict[str, float]]:
    """Train (or find) the detector of ``scenes`` training scenes and ``minutes`` from the first weights ``init``
    names; its file and its epochs and training seconds."""
    split = render_scenes(work / f"train_{scenes}", scenes, TRAIN_SEED, "industrial")
    folder = work / (f"run_{scenes}_{minutes:g}min" + ("" if init == "none" else f"_{Path(init).stem}"))
    run = train_detector([split], [1, 2, 3, 4, 5, 6], folder, replace(DEMO_DETECTOR, init=init),
                         seconds=60.0 * minutes)
    return export_detector(run.checkpoint, folder / "detector.onnx"), run_training(folder)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("runs/demo_detector_curve"))
    parser.add_argument("--runs", nargs="+", default=["150:2.5", "150:10", "600:10"], metavar="SCENES:MINUTES")
    parser.add_argument("--init", default="none", help="the detectors' first weights (detector.init)")
    parser.add_argument("--validation-scenes", type=int, default=60)
    parser.add_argument("--name", default="demo-detector-curve")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    validation = render_scenes(args.work / "validation", args.validation_scenes, VALIDATION_SEED,
                               "industrial")
    records: list[dict[str, Any]] = []
    for scenes, minutes in map(parse_run, args.runs):
        detector, training = trained_detector(args.work, scenes, minutes, args.init)
        records.append({"scenes": scenes, "minutes": minutes, **training,
                        **validation_scores(detector, validation)})
    rows = [[r["scenes"], f"{r['minutes']:g}", r["epochs"], f"{r['training_s'] / 60:.1f}", f"{r['first_epoch_s']:.1f}",
             f"{r['best_val_loss']:.3f} / {r['last_val_loss']:.3f}", *score_cells(r)] for r in records]
    markdown = "\n".join([
        f"# {args.name}: the demo's detector by training scenes and minutes",
        "",
        "`" + " ".join(["python -m experiments.demo_detector_curve", *(sys.argv[1:] if argv is None else argv)]) + "`",
        "",
        f"First weights: detector.init {args.init!r}. Validation bin split: seed {VALIDATION_SEED}, "
        f"{args.validation_scenes} scenes, industrial camera; COCO AP "
        "on amodal boxes as the BOP toolkit scores 2-D detection.",
        "",
        markdown_table(["training scenes", "budget min", "epochs", "training min", "first epoch s",
                        "validation loss best / last", "AP", "AP50", "AP75", "recall ≥ 30 % visible"], rows),
        "",
        machine_line(machine()),
    ])
    write_results(args.out, args.name, {"runs": records, "validation_scenes": args.validation_scenes}, markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    run_command("experiments.demo_detector_curve", main)
