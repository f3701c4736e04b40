"""The demo's eyes: a detector trained on the run's training scenes within a fixed share of its budget, then
scored on the cluttered test split as the BOP challenge scores detection (COCO AP on amodal boxes) and, end to
end, as it scores 6-D detection: the population code's poses from the detector's boxes alone, written by
``popcode run``'s loop as a BOP19 results file and matched to the ground truth by score
(:mod:`popcode_trainer.eval.pipeline.results_matching`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from popcode_runtime.base.files import write_json_atomic
from popcode_runtime.bop.split import split_images
from popcode_runtime.commands.detect import detect_split, detections_json
from popcode_runtime.commands.run_loop import run_detections
from popcode_runtime.inference.detector import Detector
from popcode_runtime.inference.estimator import PoseEstimator

from ..detection.export import export_detector
from ..detection.loop import train_detector
from ..eval.pipeline.evaluate import MethodResult, evaluate_models
from ..eval.pipeline.results_file import read_results_method
from ..eval.pipeline.split import EvalSplit
from ..metrics.detection_scores import DetectionScores, detection_scores
from .plan import DETECTOR_STAGE
from .steps import PipelineSize, scene_split_of

__all__ = ["DETECTIONS_FILE", "DETECTOR_STAGE", "OwnDetectorResults", "score_own_detector", "train_demo_detector"]
DETECTOR_FOLDER = "detector"
DETECTOR_FILE = "detector.onnx"
OWN_DETECTOR_FOLDER = "eval_cluttered_own_detector"
DETECTIONS_FILE = "detections.json"


@dataclass(frozen=True)
class OwnDetectorResults:
    """The demo's detector on the cluttered test split: its 2-D scores and the poses from its boxes."""

    detector: Path
    detection: DetectionScores
    poses: MethodResult | None  # None: the detector found nothing, so no pose was estimated
    mean_detect_ms: float
    first_weights: str | None = None  # which start its training took, from its metadata (None: not recorded)


def train_demo_detector(size: PipelineSize, train_split: Path, out_dir: Path, obj_ids: list[int],
                        progress: bool = True) -> Path:
    """Train (or resume) the run's detector on its training scenes for ``size.detector_seconds`` and export it."""
    folder = out_dir / DETECTOR_FOLDER
    run = train_detector([scene_split_of(train_split)], obj_ids, folder, size.detector,
                         seconds=size.detector_seconds, progress=progress)
    return export_detector(run.checkpoint, folder / DETECTOR_FILE)


def score_own_detector(detector_path: Path, popcode_models: list[Path], split_dir: Path, split: EvalSplit,
                       out_dir: Path, name: str) -> OwnDetectorResults:
    """Detect every image of ``split_dir``, score the boxes, estimate a pose in each with ``popcode_models`` and
    score those poses against every ground-truth instance (a missed part counts as wrong)."""
    folder = out_dir / OWN_DETECTOR_FOLDER
    folder.mkdir(parents=True, exist_ok=True)
    images = split_images(split_dir)
    detector = Detector(detector_path, threads=0)
    detections = detect_split(detector, images, progress=False)
    write_json_atomic(folder / DETECTIONS_FILE, detections_json(detections))
    estimators = [PoseEstimator(path) for path in popcode_models]
    results = folder / "results.csv"
    run_detections(estimators, [str(p) for p in popcode_models], images, detections, out=results,
                   fingerprint="demo", progress=False, overwrite=True)
    poses = evaluate_models([read_results_method(results, name)], split, vsd=False)[0] if detections else None
    times = {d.image_key: d.time_s for d in detections}
    mean_ms = 1000.0 * sum(times.values()) / max(len(times), 1)
    first_weights = detector.metadata.training.get("first_weights")
    return OwnDetectorResults(detector_path, detection_scores(split_dir, detections), poses, mean_ms,
                              None if first_weights is None else str(first_weights))
