"""Boxes on frames that hold no part, against recall on the bin: the shipped detector's score threshold swept.

    OMP_NUM_THREADS=1 python -m experiments.empty_frames [--work runs/empty_frames] [--detector DET.onnx]
        [--thresholds 0.2 0.25 ...] [--bins 30] [--scenes 60] [--poses] [--name empty-frames]

The empty frames (720 x 540, deterministic): uniform grey at nine levels from black to white; Gaussian noise
about mid grey at four levels and uniform noise over [0, 1] and [0.4, 0.6], three seeds each; and the first
``--bins`` images of the validation bin split (seed 4000, industrial camera) with their parts taken out, once
with their distractors and once without (``render_emptied_scenes``: the same bin, camera, lights and sensor).
The bin is the project's cluttered validation split (seed 4000, industrial, ``--scenes`` images, as
``experiments.shipped_detector`` scores the shipped detector); no test split is read. For each threshold, the
detector (``Detector`` with ``score_threshold`` overridden) gives the boxes of each kind of empty frame, and on
the bin COCO AP and AP50 as the BOP toolkit scores 2-D detection, recall at IoU 0.5 of parts at least 30 % and
90 % visible and boxes per instance; with ``--poses``, also the shipped pose models' MSSD from its boxes
(``popcode run``'s loop, every instance scored, a missed one wrong), and the same sweep over the estimate's score
that ``popcode run`` and ``FramePoseEstimator`` give (the detector's times the pose's calibrated confidence):
estimates on the empty frames against AP and recall of the bin's boxes ranked and kept by that score. Writes
``bench/results/NAME.{json,md}`` (``--name``, ``empty-frames`` by default).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.bop.detections import Detection
from popcode_runtime.bop.split import split_images
from popcode_runtime.commands.detect import detect_split
from popcode_runtime.commands.run_loop import run_detections
from popcode_runtime.geometry.crop import read_image_file
from popcode_runtime.inference.detector import DetectedBox, Detector
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.inference.frame import FramePoseEstimator
from popcode_trainer.data.render import camera_matrix
from popcode_trainer.data.scene_content import SceneSettings
from popcode_trainer.data.scene_render import render_emptied_scenes
from popcode_trainer.eval.pipeline.evaluate import evaluate_models
from popcode_trainer.eval.pipeline.results_file import read_results_method
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.detection_scores import detection_scores
from tools.command import run_command
from tools.paths import RESULTS, SHIPPED_DETECTOR, SHIPPED_MODELS
from tools.report import machine, machine_line, write_results

from .shipped_detector import render_scenes

DETECTOR = SHIPPED_DETECTOR
VALIDATION_SEED = 4000  # the project's cluttered validation seed (industrial camera)
FRAME_SIZE = (720, 540)  # the bin splits' (width, height)
GREY_LEVELS = (0, 32, 64, 96, 128, 160, 192, 224, 255)
NOISE_SIGMAS = (0.02, 0.05, 0.1, 0.2)  # Gaussian about 0.5, of the frame's [0, 1]
NOISE_SEEDS = 3
THRESHOLDS = (0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7)
# On the detector's score x the calibrated confidence: never above the detector's, so a sweep from the detector's
# lowest threshold up is exact.
ESTIMATE_THRESHOLDS = (0.2, 0.25, 0.3, 0.35, 0.4, 0.45)


def synthetic_frames(size: tuple[int, int] = FRAME_SIZE) -> dict[str, list[np.ndarray]]:
    """Frames of no structure by kind: grey levels (black and white apart) and noise, seeded per kind and seed."""
    width, height = size
    frames: dict[str, list[np.ndarray]] = {
        "black": [np.zeros((height, width), np.uint8)], "white": [np.full((height, width), 255, np.uint8)],
        "grey (7 levels)": [np.full((height, width), level, np.uint8) for level in GREY_LEVELS[1:-1]]}
    for index, sigma in enumerate(NOISE_SIGMAS):
        frames[f"Gaussian noise σ {sigma:g}"] = [
            np.clip(0.5 + np.random.default_rng([index, seed]).normal(0.0, sigma, (height, width)), 0.0, 1.0)
            .astype(np.float32) for seed in range(NOISE_SEEDS)]
    for index, (low, high) in enumerate(((0.0, 1.0), (0.4, 0.6))):
        frames[f"uniform noise [{low:g}, {high:g}]"] = [
            np.random.default_rng([len(NOISE_SIGMAS) + index, seed]).uniform(low, high, (height, width))
            .astype(np.float32) for seed in range(NOISE_SEEDS)]
    return frames


def emptied_bins(models_dir: Path, count: int) -> dict[str, list[np.ndarray]]:
    """The validation split's first ``count`` bins with their parts taken out, with and without distractors."""
    settings = SceneSettings(count, width=FRAME_SIZE[0], height=FRAME_SIZE[1], seed=VALIDATION_SEED,
                             sensor="industrial")
    return {"empty bin": render_emptied_scenes(models_dir, settings, range(count), keep_distractors=False),
            "bin of distractors only": render_emptied_scenes(models_dir, settings, range(count),
                                                             keep_distractors=True)}


def empty_frame_boxes(detector: Detector, frames: dict[str, list[np.ndarray]]) -> dict[str, list[list[DetectedBox]]]:
    """Every box on every frame, by kind (the detector's threshold bounds their scores from below)."""
    return {kind: [detector.detect(frame) for frame in group] for kind, group in frames.items()}


def highest_per_object(boxes: list[list[DetectedBox]]) -> dict[int, float]:
    """Each object's highest box score over some frames: which objects a per-object threshold would have to raise."""
    best: dict[int, float] = {}
    for box in (box for frame in boxes for box in frame):
        best[box.obj_id] = max(best.get(box.obj_id, 0.0), box.score)
    return dict(sorted(best.items()))


def boxes_above(scores: dict[str, list[list[float]]], threshold: float) -> dict[str, dict[str, int]]:
    """Per kind: frames with a box at ``threshold`` or above, and those boxes in all."""
    return {kind: {"frames": len(frames), "frames_with_boxes": sum(any(s >= threshold for s in f) for f in frames),
                   "boxes": sum(s >= threshold for f in frames for s in f)} for kind, frames in scores.items()}


def lowest_clearing(scores: dict[str, list[list[float]]], thresholds: Sequence[float]) -> float | None:
    """The lowest of ``thresholds`` at which no empty frame has a box; None when none does."""
    clearing = [t for t in sorted(thresholds)
                if not any(v["boxes"] for v in boxes_above(scores, t).values())]
    return clearing[0] if clearing else None


def bin_scores(detector: Detector, split_dir: Path, work: Path, poses: bool) -> dict[str, Any]:
    """The detector at its threshold on the bin: COCO AP, AP50, recall (IoU 0.5) of parts >= 30 % and >= 90 %
    visible, boxes per instance; with ``poses`` the shipped pose models' MSSD from its boxes."""
    images = split_images(split_dir)
    detections = detect_split(detector, images, progress=False)
    scored = detection_scores(split_dir, detections)
    visible_90 = next(r for r in scored.recall_by_visibility if r.low == 0.9)
    found: dict[str, Any] = {"AP": scored.coco["AP"], "AP50": scored.coco["AP50"],
                             "recall_30": scored.recall_goal.recall, "recall_90": visible_90.recall,
                             "boxes_per_instance": len(detections) / scored.instances, "detections": len(detections),
                             "instances": scored.instances}
    if poses:
        results = work / f"poses_{detector.score_threshold:g}.csv"
        run_detections([PoseEstimator(path) for path in SHIPPED_MODELS], [str(p) for p in SHIPPED_MODELS], images,
                       detections, out=results, fingerprint="empty_frames", progress=False, overwrite=True)
        split = read_eval_split([split_dir], split_dir / "models")
        method = evaluate_models([read_results_method(results, "popcode")], split, vsd=False)[0]
        found["MSSD"] = method.groups["All objects"]["MSSD"]
    return found


def estimate_scores(frames: FramePoseEstimator, empty: dict[str, list[np.ndarray]], split_dir: Path
                    ) -> tuple[dict[str, list[list[float]]], list[Detection]]:
    """Every estimate's score (detector's x calibrated confidence) on the empty frames by kind (seen by the bin
    splits' camera), and the bin's boxes scored so."""
    K = camera_matrix(*FRAME_SIZE)
    scores = {kind: [[pose.score for pose in frames.estimate(frame, K=K)] for frame in group]
              for kind, group in empty.items()}
    rescored = []
    for key, image in sorted(split_images(split_dir).items()):
        rescored += [Detection(*key, pose.detection.obj_id, pose.detection.box, pose.score, 0.0)
                     for pose in frames.estimate(read_image_file(image.path), K=image.K)]
    return scores, rescored


def estimate_rows(scores: dict[str, list[list[float]]], rescored: list[Detection], split_dir: Path,
                  thresholds: Sequence[float]) -> list[dict[str, Any]]:
    """Per threshold on the estimate's score: empty frames with an estimate, and the bin's AP, AP50 and recall."""
    rows = []
    for threshold in sorted(thresholds):
        kept = detection_scores(split_dir, [d for d in rescored if d.score >= threshold])
        rows.append({"threshold": threshold, "empty": boxes_above(scores, threshold),
                     "bin": {"AP": kept.coco["AP"], "AP50": kept.coco["AP50"], "recall_30": kept.recall_goal.recall}})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--work", type=Path, default=Path("runs/empty_frames"))
    parser.add_argument("--detector", type=Path, default=DETECTOR)
    parser.add_argument("--thresholds", type=float, nargs="+", default=THRESHOLDS)
    parser.add_argument("--bins", type=int, default=30, help="emptied validation bins of each kind")
    parser.add_argument("--scenes", type=int, default=60, help="images of the validation bin split")
    parser.add_argument("--poses", action="store_true", help="also the shipped pose models' MSSD from the boxes")
    parser.add_argument("--name", default="empty-frames", help="the results' name in bench/results (a candidate "
                        "detector's beside the shipped one's)")
    args = parser.parse_args()
    split_dir = render_scenes(args.work / "validation", args.scenes, VALIDATION_SEED, "industrial")
    frames = {**synthetic_frames(), **emptied_bins(split_dir / "models", args.bins)}
    lowest = min(args.thresholds)
    boxes = empty_frame_boxes(Detector(args.detector, threads=1, score_threshold=lowest), frames)
    scores = {kind: [[box.score for box in frame] for frame in group] for kind, group in boxes.items()}
    rows = []
    for threshold in sorted(args.thresholds):
        detector = Detector(args.detector, threads=1, score_threshold=threshold)
        rows.append({"threshold": threshold, "empty": boxes_above(scores, threshold),
                     "bin": bin_scores(detector, split_dir, args.work, args.poses)})
    estimates: list[dict[str, Any]] = []
    if args.poses:
        frame_estimator = FramePoseEstimator(Detector(args.detector, threads=1, score_threshold=lowest),
                                             [PoseEstimator(path, threads=1) for path in SHIPPED_MODELS])
        estimates = estimate_rows(*estimate_scores(frame_estimator, frames, split_dir), split_dir,
                                  [t for t in ESTIMATE_THRESHOLDS if t >= lowest])
    payload = {"command": shlex.join(["python", "-m", "experiments.empty_frames", *sys.argv[1:]]),
               "threads": os.environ.get("OMP_NUM_THREADS"), "arguments": {k: str(v) for k, v in vars(args).items()},
               "file_threshold": Detector(args.detector).metadata.score_threshold,
               "max_score": {kind: max((s for f in group for s in f), default=None) for kind, group in scores.items()},
               "max_score_per_object": {kind: highest_per_object(group) for kind, group in boxes.items()},
               "lowest_clearing_threshold": lowest_clearing(scores, args.thresholds), "rows": rows,
               "estimate_rows": estimates}
    write_results(RESULTS, args.name, payload, _markdown(payload, lowest))


def _markdown(payload: dict[str, Any], lowest: float) -> str:
    rows = payload["rows"]
    thresholds = [f"{row['threshold']:g}" for row in rows]
    empty = markdown_table(
        ["empty frames", f"highest score (boxes ≥ {lowest:g})", *(f"≥ {t}" for t in thresholds)],
        [[kind, "–" if top is None else f"{top:.3f}",
          *(f"{row['empty'][kind]['frames_with_boxes']}/{row['empty'][kind]['frames']}" for row in rows)]
         for kind, top in payload["max_score"].items()])
    per_object = markdown_table(["empty frames", "highest score of each object (object: score)"], [
        [kind, ", ".join(f"{obj_id}: {score:.2f}" for obj_id, score in best.items()) or "–"]
        for kind, best in payload["max_score_per_object"].items()])
    poses = "MSSD" in rows[0]["bin"]
    bin_rows = markdown_table(
        ["threshold", "AP", "AP50", "recall ≥ 30 % visible", "recall ≥ 90 % visible", "boxes / instance",
         *(["MSSD from its boxes"] if poses else [])],
        [[t, *(f"{100 * row['bin'][key]:.1f}" for key in ("AP", "AP50", "recall_30", "recall_90")),
          f"{row['bin']['boxes_per_instance']:.2f}", *([f"{100 * row['bin']['MSSD']:.1f}"] if poses else [])]
         for t, row in zip(thresholds, rows, strict=True)])
    clearing = payload["lowest_clearing_threshold"]
    needs = markdown_table(["empty frames", "lowest threshold without a box", "recall ≥ 30 % visible there",
                            "AP there"], [
        [kind, *next(([f"{row['threshold']:g}", f"{100 * row['bin']['recall_30']:.1f}",
                       f"{100 * row['bin']['AP']:.1f}"] for row in rows if not row["empty"][kind]["boxes"]),
                     ["above the sweep", "–", "–"])] for kind in payload["max_score"]])
    estimates = []
    if payload["estimate_rows"]:
        kinds = list(payload["max_score"])
        estimates = [
            "Thresholds on the estimate's score (detector's x calibrated confidence, as `popcode run` scores and "
            "ranks an estimate): empty frames with an estimate, and the bin's boxes ranked and kept by that score:",
            markdown_table(["estimate score ≥", *kinds, "AP", "AP50", "recall ≥ 30 % visible"], [
                [f"{row['threshold']:g}", *(f"{row['empty'][k]['frames_with_boxes']}/{row['empty'][k]['frames']}"
                                            for k in kinds),
                 *(f"{100 * row['bin'][key]:.1f}" for key in ("AP", "AP50", "recall_30"))]
                for row in payload["estimate_rows"]])]
    return "\n\n".join([
        "# Boxes on empty frames against recall on the bin (`python -m experiments.empty_frames`)",
        f"Command: `{payload['command']}` (OMP_NUM_THREADS={payload['threads']}); validation data only (the bin "
        f"split of seed {VALIDATION_SEED} and its emptied images, seeded noise).",
        f"The detector's file threshold: {payload['file_threshold']:g}. The lowest threshold of the sweep at which "
        f"no empty frame has a box: {'none' if clearing is None else f'{clearing:g}'}.",
        "Empty frames with a box, by the score threshold:", empty,
        "What each kind of empty frame needs, and what the bin keeps at that threshold:", needs,
        "Which objects the boxes name (the metadata carries one threshold for every object):", per_object,
        f"The validation bin ({rows[0]['bin']['instances']} instances), by the score threshold:", bin_rows,
        *estimates, machine_line(machine())])


if __name__ == "__main__":
    run_command("experiments.empty_frames", main)
