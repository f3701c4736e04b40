"""Models (checkpoints or ONNX files) + a BOP split -> per-instance errors and the paper's tables.

Rotation from the model, translation from the ground truth (the paper's
protocol); optionally also full 6-D poses, with the translation fitted to the
box as the runtime does it (:mod:`.translation`). Every method is scored on the
same instances, those all of them can estimate, with the object meshes and depth
renderers of one :class:`.split_metrics.SplitMetrics`.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from popcode_runtime.errors import PopcodeError

from ..metrics.recall import InstanceErrors, Thresholds
from .models import Method, predict_rotations
from .split import EvalSplit, restrict_to_objects
from .split_metrics import SplitMetrics
from .translation import FullPose, full_pose


@dataclass(frozen=True)
class MethodResult:
    """What one method scored on the split; scores are fractions in [0, 1]."""

    name: str
    split: EvalSplit  # the instances scored, in the order of every per-instance array
    model_paths: tuple[str, ...]
    R_est: np.ndarray  # (N, 3, 3), split order
    errors: InstanceErrors
    per_object: dict[int, dict[str, float]]
    groups: dict[str, dict[str, float]]
    tightest: dict[str, dict[str, float]]  # per group, the recall at each metric's tightest threshold
    model_ms_per_crop: float  # crop + network + decoding; NaN for given rotations
    metric_s: float
    full_pose: FullPose | None = None  # when asked for: translation from the box, 6-D scores
    thresholds: Thresholds = field(default_factory=Thresholds)  # those every score was computed with


def evaluate_rotations(name: str, R_est: np.ndarray, metrics: SplitMetrics, model_paths: tuple[str, ...] = (),
                       model_ms_per_crop: float = float("nan"),
                       points_mm: Mapping[int, np.ndarray] | None = None) -> MethodResult:
    """Score given rotations (one per split instance): the path for precomputed estimates.

    With ``points_mm`` (object id -> points the runtime fits to a box) full 6-D
    poses are scored too, the translation fitted to each instance's box.
    """
    started = time.perf_counter()
    R_est = np.asarray(R_est, np.float64)
    errors = metrics.errors(R_est)
    per_object, groups = metrics.scores(errors)
    pose = None if points_mm is None else full_pose(R_est, metrics, points_mm)
    return MethodResult(name, metrics.split, model_paths, R_est, errors, per_object, groups, metrics.tightest(errors),
                        model_ms_per_crop, time.perf_counter() - started, pose, metrics.thresholds)


def evaluate_model(method: Method, metrics: SplitMetrics, progress: bool = True,
                   points_mm: Mapping[int, np.ndarray] | None = None) -> MethodResult:
    """Predict every instance of the split with the method's models, then score (6-D too with ``points_mm``)."""
    R_est, model_s_per_crop = predict_rotations(method, metrics.split.instances, progress)
    return evaluate_rotations(method.name, R_est, metrics, tuple(str(m.path) for m in method.models),
                              1000.0 * model_s_per_crop, points_mm)


def _shared_split(methods: Sequence[Method], split: EvalSplit, obj_ids: Iterable[int] | None) -> EvalSplit:
    """The instances every method can estimate, so that all rows of a table score the same instances.

    With ``obj_ids`` every method must know each of them; without, objects some
    method lacks are left out with a warning.
    """
    known = [set(method.model_of()) for method in methods]
    if obj_ids is not None:
        wanted = set(obj_ids)
        for method, objects in zip(methods, known, strict=True):
            lacking = sorted(wanted - objects)
            if lacking:
                raise PopcodeError(f"method {method.name!r} has no model for objects {lacking} "
                                   f"(its models know {sorted(objects)})")
    shared = set.intersection(*known) & set(split.obj_ids)
    if not shared:
        raise PopcodeError(f"no object of the split ({split.obj_ids}) is known to every model: "
                           + "; ".join(f"{m.name!r} knows {sorted(o)}" for m, o in zip(methods, known, strict=True)))
    left_out = sorted(set(split.obj_ids) - shared)
    if left_out:
        warnings.warn(f"objects {left_out} of the split are not known to every model and are not evaluated",
                      stacklevel=3)
    return restrict_to_objects(split, shared)


def evaluate_models(methods: Sequence[Method], split: EvalSplit, thresholds: Thresholds | None = None,
                    vsd: bool | None = None, obj_ids: Iterable[int] | None = None,
                    progress: bool = True, translation: bool = False) -> list[MethodResult]:
    """Every method on the same split instances, sharing object models and depth renderers.

    ``translation`` also fits each instance's translation to its box, as the
    runtime does, and scores the full 6-D poses (:class:`FullPose`).
    """
    if not methods:
        raise PopcodeError("no models to evaluate")
    # Every model's object points before the first prediction: a model without them fails now, not after hours.
    points_mm = [method.object_points() if translation else None for method in methods]
    metrics = SplitMetrics(_shared_split(methods, split, obj_ids), thresholds, vsd)
    try:
        return [evaluate_model(method, metrics, progress, points) for method, points in zip(methods, points_mm,
                                                                                            strict=True)]
    finally:
        metrics.close()
