"""Train the shipped detector of the six built-in parts and measure it: AP on a validation and an unseen bin split,
the bin's MSSD end to end from its boxes beside the true and detector-like boxes, and the whole frame's latency.

    python -m experiments.shipped_detector [--work runs/shipped_detector] [--epochs 40] [--scenes 600 900]
        [--set detector.KEY=VALUE ...] [--copy-to models/builtin-parts-detector.onnx] [--measure-only]

Renders the training scenes (seed 21 without a sensor model, seed 22 with the industrial camera's noise, blur
and exposure, as the demo's scenes; the sizes given by ``--scenes``), a validation bin split (seed 4000,
industrial, 60 scenes: the project's cluttered validation seed) and the unseen bin split the shipped pose
models are scored on (seed 6002, industrial, 30 scenes: ``models/README.md``); trains ``popcode-train
train-detector`` for ``--epochs`` (rerun to resume: every step keeps what it finished); exports; scores the
detector on both bin splits (COCO AP as the BOP toolkit) and the shipped pose models from its boxes
(``popcode run``'s loop, matched by score as the toolkit does), and times the detector and ten parts' poses on
the unseen split's frames with the runtime (two threads). Writes ``bench/results/shipped-detector.{json,md}``.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.bop.split import split_images
from popcode_runtime.geometry.crop import read_image
from popcode_runtime.inference.frame import FramePoseEstimator
from popcode_trainer.data.box_noise import box_noise_preset
from popcode_trainer.demo.detector_step import score_own_detector
from popcode_trainer.eval.pipeline.detector_boxes import with_detector_boxes
from popcode_trainer.eval.pipeline.evaluate import MethodResult, evaluate_models
from popcode_trainer.eval.pipeline.models import Method, load_model
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.paths import RESULTS, SHIPPED_MODELS
from tools.report import machine, machine_line, write_results

TRAIN_SEEDS = (21, 22)  # the first without a sensor model, the second with the industrial camera's
SPLITS = {"validation": (4000, 60), "unseen": (6002, 30)}  # seed, scenes (industrial camera)
FRAME_PARTS = 10  # the poses a frame's latency counts


def _render(out: Path, scenes: int, seed: int, sensor: str) -> Path:
    if not (out / "000000" / "scene_gt.json").is_file():
        subprocess.run([sys.executable, "-m", "popcode_trainer.cli", "render", "--objects", "builtin", "--out",
                        str(out), "--scenes", str(scenes), "--seed", str(seed), "--sensor", sensor, "--quiet"],
                       check=True)
    return out


def _mssd(result: MethodResult) -> dict[str, Any]:
    return {"MSSD": result.groups["All objects"]["MSSD"], "per_object": {
        name: values["MSSD"] for name, values in result.groups.items() if name != "All objects"},
        "by_visibility": {label: values["MSSD"] for label, values in result.by_visibility.items()}}


def _score_split(detector: Path, split_dir: Path, work: Path) -> dict[str, Any]:
    split = read_eval_split([split_dir], split_dir / "models")
    method = Method("popcode", tuple(load_model(path) for path in SHIPPED_MODELS))
    true_boxes = evaluate_models([method], split, vsd=False)[0]
    noisy = evaluate_models([method], with_detector_boxes(split, box_noise_preset("detector"), seed=0), vsd=False)[0]
    own = score_own_detector(detector, list(SHIPPED_MODELS), split_dir, split, work, "popcode, own detector")
    return {"detection": own.detection.to_dict(), "mean_detect_ms": own.mean_detect_ms,
            "mssd": {"true boxes": _mssd(true_boxes), "detector-like boxes": _mssd(noisy),
                     "own detector": None if own.poses is None else _mssd(own.poses)}}


def _frame_latency(detector: Path, split_dir: Path) -> dict[str, float]:
    """Median ms of the detector on each frame, and of the pose models on ten of its boxes (repeated where it
    found fewer), two threads, after a warm-up."""
    frames = FramePoseEstimator.from_files(detector, list(SHIPPED_MODELS), threads=2)
    images = [read_image(image.path) for image in split_images(split_dir).values()]
    detect_ms, poses_ms = [], []
    for image in [images[0], *images]:
        found = frames.detector.detect(image)
        detect_ms.append(1000 * frames.detector.last_seconds)
        boxes = [found[i % len(found)] for i in range(FRAME_PARTS)] if found else []
        started = time.perf_counter()
        for model in frames.estimators:
            mine = [d for d in boxes if d.obj_id in model.metadata.objects]
            if mine:
                model.predict(image, [d.box for d in mine], K=split_images(split_dir)[(0, 0)].K,
                              obj_ids=[d.obj_id for d in mine], translation=True)
        poses_ms.append(1000 * (time.perf_counter() - started))
    detect, poses = float(np.median(detect_ms[1:])), float(np.median(poses_ms[1:]))
    return {"detect_ms": detect, "ten_poses_ms": poses, "frame_ms": detect + poses}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("runs/shipped_detector"))
    parser.add_argument("--epochs", type=int, default=40)
    parser.add_argument("--scenes", type=int, nargs=2, default=(600, 900), metavar=("PLAIN", "INDUSTRIAL"))
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="detector.KEY=VALUE")
    parser.add_argument("--copy-to", type=Path, help="copy the exported detector here")
    parser.add_argument("--measure-only", action="store_true", help="score the detector already in WORK/run")
    args = parser.parse_args()
    work = args.work
    train = [_render(work / f"train_{seed}", scenes, seed, sensor) for seed, scenes, sensor
             in zip(TRAIN_SEEDS, args.scenes, ("none", "industrial"), strict=True)]
    splits = {name: _render(work / name, scenes, seed, "industrial") for name, (seed, scenes) in SPLITS.items()}
    run = work / "run"
    started = time.perf_counter()
    if not args.measure_only:
        subprocess.run([sys.executable, "-m", "popcode_trainer.cli", "train-detector", *(
            item for split in train for item in ("--split", str(split))), "--out", str(run), "--set",
            f"detector.epochs={args.epochs}", *(item for o in args.overrides for item in ("--set", o))], check=True)
    detector = run / "detector.onnx"
    if args.copy_to:
        shutil.copyfile(detector, args.copy_to)
    scores = {name: _score_split(detector, split, work / f"scored_{name}") for name, split in splits.items()}
    latency = _frame_latency(detector, splits["unseen"])
    payload = {"arguments": {k: str(v) for k, v in vars(args).items()}, "train_seconds": time.perf_counter() - started,
               "scores": scores, "latency": latency}
    write_results(RESULTS, "shipped-detector", payload, _markdown(payload))


def _markdown(payload: dict[str, Any]) -> str:
    rows, mssd_rows = [], []
    for name, found in payload["scores"].items():
        det = found["detection"]
        rows.append([name, *(f"{100 * (det.get(k) or 0):.1f}" for k in ("AP", "AP50", "AP75", "AR100")),
                     f"{100 * det['recall_iou50_goal']['recall']:.1f}", f"{found['mean_detect_ms']:.0f}"])
        for boxes, scored in found["mssd"].items():
            if scored is not None:
                mssd_rows.append([name, boxes, f"{100 * scored['MSSD']:.1f}",
                                  *(f"{100 * v:.1f}" for v in scored["by_visibility"].values())])
    bins = list(next(iter(payload["scores"].values()))["mssd"]["true boxes"]["by_visibility"])
    latency = payload["latency"]
    return "\n\n".join([
        "# The shipped detector (`python -m experiments.shipped_detector`)",
        markdown_table(["bin split", "AP", "AP50", "AP75", "AR100", "recall ≥ 30 % visible", "ms/frame"], rows),
        "MSSD of the shipped pose models (argmax) by where the boxes came from (own detector: every instance, a "
        "missed one wrong, matched by score as the BOP toolkit does):",
        markdown_table(["bin split", "boxes", "MSSD", *(f"visib {b}" for b in bins)], mssd_rows),
        f"Whole frame, two threads, median over the unseen split's frames: detector {latency['detect_ms']:.1f} ms "
        f"+ {FRAME_PARTS} parts' poses {latency['ten_poses_ms']:.1f} ms = {latency['frame_ms']:.1f} ms.",
        machine_line(machine()),
    ])


if __name__ == "__main__":
    run_command("experiments.shipped_detector", main)
