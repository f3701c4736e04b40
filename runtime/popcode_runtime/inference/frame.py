"""``FramePoseEstimator``: a camera frame -> every part's pose, the one object a robot's loop calls.

The detector finds the parts (:class:`~popcode_runtime.inference.detector.Detector`); each box goes to the pose
model that knows its object (the routing of :mod:`popcode_runtime.inference.image_loop`), all of a model's boxes
in one :meth:`PoseEstimator.predict` call, with the translation from the box or, given a depth image, from the
observed surface (and refined against it when asked).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.errors import PopcodeError
from .detector import DetectedBox, Detector
from .estimator import PoseEstimator
from .image_loop import route_objects
from .prediction import Prediction


@dataclass(frozen=True)
class FramePose:
    """One part of a frame: what the detector saw and the pose estimated in its box."""

    detection: DetectedBox
    prediction: Prediction

    @property
    def score(self) -> float:
        """The detector's score times the pose's calibrated confidence where the model has one (as ``popcode run``
        scores an estimate)."""
        confidence = self.prediction.confidence
        return self.detection.score * (1.0 if confidence is None else confidence)


@dataclass
class FrameTimings:
    """Seconds of the last frame: the detector (resize to boxes) and the pose models (crop to pose)."""

    detect_s: float = 0.0
    poses_s: float = 0.0


class FramePoseEstimator:
    """``estimate(image, K)`` -> a :class:`FramePose` per part found, best detection first.

    Build it from files with :meth:`from_files` or from a :class:`Detector` and
    :class:`PoseEstimator` objects. A detector none of whose objects a pose
    model knows is refused when built; boxes of objects no given model knows
    are skipped and counted, per object, in :attr:`last_skipped` (as ``popcode
    run`` and ``popcode predict --detector`` count them).
    """

    def __init__(self, detector: Detector, estimators: Sequence[PoseEstimator], names: Sequence[str] | None = None
                 ) -> None:
        if not estimators:
            raise PopcodeError("a frame estimator needs at least one pose model")
        names = list(names) if names is not None else [f"pose model {i}" for i in range(len(estimators))]
        self.detector, self.estimators = detector, list(estimators)
        self._owner = route_objects(self.estimators, names)
        if not set(detector.obj_ids) & set(self._owner):
            raise PopcodeError(f"the detector finds objects {list(detector.obj_ids)} and the pose models know objects "
                               f"{sorted(self._owner)}: none in common (wrong detector or wrong models?)")
        self.last_timings = FrameTimings()
        self.last_skipped: dict[int, int] = {}  # the last frame's boxes no pose model knows, by object id

    @classmethod
    def from_files(cls, detector_path: str | Path, model_paths: Sequence[str | Path],
                   providers: Sequence[str] | None = None, threads: int = 0, decoder: str = "argmax",
                   **detector_options: float) -> FramePoseEstimator:
        """A frame estimator of a detector file and pose model files (``detector_options``: ``score_threshold``,
        ``nms_iou``, ``max_detections`` instead of the file's)."""
        detector = Detector(detector_path, providers, threads, **detector_options)
        estimators = [PoseEstimator(path, providers, threads, decoder) for path in model_paths]
        return cls(detector, estimators, [str(path) for path in model_paths])

    @property
    def unknown_objects(self) -> list[int]:
        """The detector's objects no pose model knows: their boxes are skipped."""
        return sorted(set(self.detector.obj_ids) - set(self._owner))

    def estimate(self, image: np.ndarray, K: Sequence[float] | np.ndarray | None = None, top_k: int = 1,
                 depth: np.ndarray | None = None, depth_scale: float = 1.0, refine_depth: bool = False,
                 translation: bool | None = None, return_code: bool = False) -> list[FramePose]:
        """Every part the detector finds in ``image`` and its pose, as :meth:`PoseEstimator.predict` gives it
        (``translation``: default, whenever ``K`` is given; from ``depth`` when given). A frame with no parts gives
        ``[]``."""
        started = time.perf_counter()
        found = self.detector.detect(image)
        detected = time.perf_counter()
        poses: list[FramePose] = []
        for index, estimator in enumerate(self.estimators):
            mine = [d for d in found if self._owner.get(d.obj_id) == index]
            if not mine:
                continue
            predictions = estimator.predict(image, [d.box for d in mine], K=K, obj_ids=[d.obj_id for d in mine],
                                            top_k=top_k, depth=depth, depth_scale=depth_scale,
                                            refine_depth=refine_depth, return_code=return_code,
                                            translation=K is not None if translation is None else translation)
            poses += [FramePose(d, p) for d, p in zip(mine, predictions, strict=True)]
        self.last_skipped = dict(sorted(Counter(d.obj_id for d in found if d.obj_id not in self._owner).items()))
        self.last_timings = FrameTimings(detected - started, time.perf_counter() - detected)
        return sorted(poses, key=lambda pose: -pose.detection.score)
