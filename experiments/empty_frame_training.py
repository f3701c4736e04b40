"""Does training the quick demo's detector with frames without parts (``render --empty-share``) lower its boxes
on empty frames, at equal AP on the bin?

    OMP_NUM_THREADS=1 python -m experiments.empty_frame_training [--work runs/empty_frame_training]
        [--shares 0 0.2] [--seeds 0 1] [--scenes 150] [--minutes 2.5] [--init auto] [--thresholds 0.3 0.4 0.5]
        [--bins 30]

For each share, the demo's training scenes (``--scenes``, seed 3000, industrial camera) are rendered with that share
of them without parts: the images that hold parts are the same ones in every split (an image is drawn from its
index), the rest are empty bins, half with their distractors. ``popcode_trainer.demo.sizes.DEMO_DETECTOR`` is
trained on each from the first weights ``--init`` names (``auto``: the shipped detector start, as the demo trains
it), once per training seed (``detector.seed``: the held-out images, augmentation and order); the first run fits
its epochs to ``--minutes`` on this machine, the others train as many epochs (the same number of frames each epoch,
so the same number of steps). Each detector is scored at each threshold on the
empty frames of ``experiments.empty_frames`` (grey levels, noise, the first ``--bins`` validation bins emptied with
and without distractors) and on the validation bin split (seed 4000, 60 images; COCO AP as the BOP toolkit scores
2-D detection, recall at IoU 0.5 of parts at least 30 % visible). No test split is read. Results:
``bench/results/empty-frame-training.{json,md}``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

from experiments.empty_frames import (
    VALIDATION_SEED,
    bin_scores,
    boxes_above,
    emptied_bins,
    empty_frame_boxes,
    synthetic_frames,
)
from experiments.shipped_detector import render_scenes, run_training
from popcode_runtime.inference.detector import Detector
from popcode_trainer.demo.sizes import DEMO_DETECTOR
from popcode_trainer.detection.export import export_detector
from popcode_trainer.detection.loop import train_detector
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

TRAIN_SEED = 3000  # the demo's training scenes
VALIDATION_SCENES = 60


def trained(work: Path, scenes: int, share: float, seed: int, init: str, minutes: float | None, epochs: int | None
            ) -> tuple[Path, dict[str, float]]:
    """The detector trained with ``seed`` on ``scenes`` training scenes, ``share`` of them empty, for ``minutes`` (its
    epochs fitted) or ``epochs``; its file and its training (a rerun finds it)."""
    name = f"train_{scenes}" + (f"_empty{share:g}" if share else "")
    split = render_scenes(work / name, scenes, TRAIN_SEED, "industrial", share)
    folder = work / (f"run_{name}" + (f"_seed{seed}" if seed else ""))
    config = replace(DEMO_DETECTOR, init=init, epochs=epochs or DEMO_DETECTOR.epochs, seed=seed)
    run = train_detector([split], [1, 2, 3, 4, 5, 6], folder, config,
                         seconds=None if minutes is None else 60.0 * minutes)
    return export_detector(run.checkpoint, folder / "detector.onnx"), run_training(folder)


def scores(detector: Path, frames: dict, split_dir: Path, work: Path, thresholds: list[float]) -> list[dict]:
    """Per threshold: frames of each kind with a box, and the bin's AP, recall and boxes per instance."""
    boxes = empty_frame_boxes(Detector(detector, threads=1, score_threshold=min(thresholds)), frames)
    found = {kind: [[box.score for box in frame] for frame in group] for kind, group in boxes.items()}
    return [{"threshold": t, "empty": boxes_above(found, t),
             "bin": bin_scores(Detector(detector, threads=1, score_threshold=t), split_dir, work, poses=False)}
            for t in sorted(thresholds)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("runs/empty_frame_training"))
    parser.add_argument("--shares", type=float, nargs="+", default=[0.0, 0.2])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--scenes", type=int, default=150)
    parser.add_argument("--minutes", type=float, default=2.5)
    parser.add_argument("--init", default="auto")
    parser.add_argument("--thresholds", type=float, nargs="+", default=[0.3, 0.4, 0.5])
    parser.add_argument("--bins", type=int, default=30)
    args = parser.parse_args()
    split_dir = render_scenes(args.work / "validation", VALIDATION_SCENES, VALIDATION_SEED, "industrial")
    frames = {**synthetic_frames(), **emptied_bins(split_dir / "models", args.bins)}
    runs, epochs = [], None
    for seed in args.seeds:
        for share in args.shares:
            detector, training = trained(args.work, args.scenes, share, seed, args.init,
                                         args.minutes if epochs is None else None, epochs)
            epochs = epochs or int(training["epochs"])
            runs.append({"share": share, "seed": seed, "training": training,
                         "rows": scores(detector, frames, split_dir, args.work, args.thresholds)})
    payload = {"command": shlex.join(["python", "-m", "experiments.empty_frame_training", *sys.argv[1:]]),
               "threads": os.environ.get("OMP_NUM_THREADS"), "arguments": {k: str(v) for k, v in vars(args).items()},
               "runs": runs}
    write_results(RESULTS, "empty-frame-training", payload, _markdown(payload))


def _markdown(payload: dict[str, Any]) -> str:
    runs = payload["runs"]
    kinds = list(runs[0]["rows"][0]["empty"])
    synthetic = [kind for kind in kinds if "bin" not in kind]
    training = markdown_table(["empty share", "seed", "epochs", "training s", "last val loss"], [
        [f"{run['share']:g}", str(run["seed"]), f"{run['training']['epochs']:.0f}",
         f"{run['training']['training_s']:.0f}", f"{run['training']['last_val_loss']:.3f}"] for run in runs])

    def with_box(row: dict, chosen: list[str]) -> str:
        found, frames = (sum(row["empty"][k][key] for k in chosen) for key in ("frames_with_boxes", "frames"))
        return f"{found}/{frames}"

    by_threshold = markdown_table(
        ["threshold", "empty share", "seed", "AP", "AP50", "recall ≥ 30 % visible", "boxes / instance",
         "grey and noise frames with a box", "empty bins with a box", "distractor-only bins with a box"],
        [[f"{row['threshold']:g}", f"{run['share']:g}", str(run["seed"]), *(f"{100 * row['bin'][k]:.1f}" for k in
                                                          ("AP", "AP50", "recall_30")),
          f"{row['bin']['boxes_per_instance']:.2f}", with_box(row, synthetic), with_box(row, ["empty bin"]),
          with_box(row, ["bin of distractors only"])]
         for index in range(len(runs[0]["rows"])) for run in runs for row in [run["rows"][index]]])
    per_kind = markdown_table(
        ["empty frames", *(f"share {run['share']:g} seed {run['seed']} @ {row['threshold']:g}"
                           for row in runs[0]["rows"] for run in runs)],
        [[kind, *(f"{run['rows'][i]['empty'][kind]['frames_with_boxes']}/{run['rows'][i]['empty'][kind]['frames']}"
                  for i in range(len(runs[0]["rows"])) for run in runs)] for kind in kinds])
    return "\n\n".join([
        "# Training the quick demo's detector with frames without parts (`python -m experiments.empty_frame_training`)",
        f"Command: `{payload['command']}` (OMP_NUM_THREADS={payload['threads']}); validation data only (the bin "
        f"split of seed {VALIDATION_SEED} and its emptied images, seeded noise).",
        "The runs:", training, "Boxes on empty frames and the bin's scores, by threshold:", by_threshold,
        "Empty frames with a box, by kind:", per_kind, machine_line(machine())])


if __name__ == "__main__":
    run_command("experiments.empty_frame_training", main)
