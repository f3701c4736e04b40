"""Models (checkpoints or ONNX files) + a BOP split -> per-instance errors and the paper's tables.

Rotation from the model, translation from the ground truth (the paper's
protocol); optionally also full 6-D poses, with the translation fitted to the
box as the runtime does it (:mod:`.translation`) and, for a split with depth
images, from the depth (and refined against it) as the runtime does it
(:mod:`.depth_poses`). Every method is scored on the
same instances, those all of them can estimate, with the object meshes and depth
renderers of one :class:`.split_metrics.SplitMetrics`. A split whose boxes are a
detector's (:func:`.detector_boxes.with_detector_boxes`) is also scored per box
IoU; with ``top_k > 1`` population codes are also scored by the best of their
top-k hypotheses. A results file's estimates are matched to the instances as
the BOP toolkit matches them (:mod:`.results_matching`).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from popcode_runtime.base.checks import integer
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.confidence import DEFAULT_THRESHOLD_DEG
from popcode_runtime.inference.request import MAX_TOP_K

from ...metrics.confidence import ConfidenceEvaluation, evaluate_confidence, rotation_errors_deg
from ...metrics.recall import InstanceErrors, Thresholds, metric_scores
from .depth_poses import DepthMode, DepthPoses, check_depth_models, depth_modes, depth_poses, require_depth
from .estimates import Estimates
from .models import Method
from .results_file import ResultsMethod
from .results_matching import ResultsMatching, group_results, matched_errors
from .split import EvalSplit, restrict_to_objects
from .split_metrics import SplitMetrics
from .translation import FullPose, full_pose


@dataclass(frozen=True)
class BestOfTopK:
    """MSSD of the best of each instance's first k candidate rotations (:attr:`Estimates.hypotheses`), k = 1..K.

    The best candidate is the one of smallest MSSD error (the first of equals); k = 1 is the plain estimate.
    """

    mssd_mm: np.ndarray  # (K, N) row k - 1: the MSSD error [mm] of the best of the first k, split order
    groups: dict[int, dict[str, float]]  # k -> ambiguity group -> MSSD score in [0, 1]


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
    confidence: ConfidenceEvaluation | None = None  # how well the per-estimate score predicts a small error
    by_visibility: dict[str, dict[str, float]] = field(default_factory=dict)  # visib_fract bin -> scores, count
    by_box_iou: dict[str, dict[str, float]] = field(default_factory=dict)  # IoU bin -> scores, count; detector boxes
    top_k: int = 1  # hypotheses asked for
    best_of_top_k: BestOfTopK | None = None  # with top_k > 1, for population codes
    score: np.ndarray | None = None  # (N,) each estimate's score (Estimates.bop19_score); None: given rotations
    image_s: np.ndarray | None = None  # (N,) seconds of the estimates of the instance's image; None: given rotations
    depth_poses: tuple[DepthPoses, ...] = ()  # with depth: the 6-D poses of each depth mode, beside full_pose's
    look_alikes: dict[int, np.ndarray] = field(default_factory=dict)  # SplitMetrics.look_alikes
    decoder: str | None = None  # how the models' outputs became rotations; None: given rotations, a results file
    matching: ResultsMatching | None = None  # a results file's: its instances without an estimate, ignored estimates


def best_of_top_k(hypotheses: np.ndarray, errors: InstanceErrors, metrics: SplitMetrics) -> BestOfTopK:
    """Score the best of the first k of ``hypotheses (K, N, 3, 3)`` for every k, rank 0 having ``errors``.

    Each further rank is scored once, without the depth-based errors: MSSD picks the best.
    """
    ranks = [errors.mssd_mm] + [metrics.errors(R, depth=False).mssd_mm for R in hypotheses[1:]]
    best = np.minimum.accumulate(np.stack(ranks), axis=0)
    groups = {}
    for k, mssd_mm in enumerate(best, start=1):
        scores = metrics.scores(dataclasses.replace(errors, mssd_mm=mssd_mm))[1]
        groups[k] = {group: values["MSSD"] for group, values in scores.items()}
    return BestOfTopK(best, groups)


def evaluate_rotations(name: str, R_est: np.ndarray, metrics: SplitMetrics, model_paths: tuple[str, ...] = (),
                       model_ms_per_crop: float = float("nan"),
                       points_mm: Mapping[int, np.ndarray] | None = None,
                       errors: InstanceErrors | None = None) -> MethodResult:
    """Score given rotations (one per split instance): the path for precomputed estimates.

    With ``points_mm`` (object id -> points the runtime fits to a box) full 6-D
    poses are scored too, the translation fitted to each instance's box.
    ``errors`` replaces the rotations' own errors where they are not what is
    scored: a results file's, credited by the toolkit's matching (``R_est`` then
    NaN where an instance has no estimate).
    """
    started = time.perf_counter()
    R_est = np.asarray(R_est, np.float64)
    errors = metrics.errors(R_est) if errors is None else errors
    per_object, groups = metrics.scores(errors)
    pose = None if points_mm is None else full_pose(R_est, metrics, points_mm)
    return MethodResult(name, metrics.split, model_paths, R_est, errors, per_object, groups, metrics.tightest(errors),
                        model_ms_per_crop, time.perf_counter() - started, pose, metrics.thresholds,
                        by_visibility=metrics.by_visibility(errors), by_box_iou=metrics.by_box_iou(errors),
                        look_alikes=metrics.look_alikes)


def evaluate_model(method: Method | ResultsMethod, metrics: SplitMetrics, progress: bool = True,
                   points_mm: Mapping[int, np.ndarray] | None = None, top_k: int = 1,
                   modes: Sequence[DepthMode] = ()) -> MethodResult:
    """Estimate every instance of the split with the method (run its models, or read its results file), then
    score (6-D too with ``points_mm``, the object points of model files; with ``top_k > 1`` the best of the
    top-k hypotheses of a population code too; in each depth mode of ``modes`` the 6-D poses from depth: model
    files only)."""
    split = metrics.split
    estimates = method.estimate(split.instances, split.models_info, progress, top_k)
    matching = group_results(method.estimates, split.instances) if isinstance(method, ResultsMethod) else None
    result = evaluate_rotations(method.name, estimates.R_m2c, metrics, method.paths,
                                1000.0 * estimates.seconds_per_crop, points_mm,
                                None if matching is None else matched_errors(matching, metrics))
    best = None
    if estimates.hypotheses is not None:
        started = time.perf_counter()
        best = best_of_top_k(estimates.hypotheses, result.errors, metrics)
        result = dataclasses.replace(result, metric_s=result.metric_s + time.perf_counter() - started)
    posed = tuple(depth_poses(method, metrics, mode, top_k, progress) for mode in modes)
    return dataclasses.replace(result, confidence=confidence_evaluation(estimates, metrics, result.errors,
                                                                        method.confidence_thresholds_deg),
                               top_k=top_k, best_of_top_k=best, score=estimates.bop19_score(),
                               image_s=estimates.image_s, depth_poses=posed,
                               decoder=method.decoder if isinstance(method, Method) else None, matching=matching)


def confidence_evaluation(estimates: Estimates, metrics: SplitMetrics, errors: InstanceErrors,
                          thresholds_deg: set[float | None]) -> ConfidenceEvaluation | None:
    """The calibrated confidence when every model of the method has one (and all share a threshold), else the
    raw score at the default threshold; judged on the instances with an estimate (a results file may miss some),
    None without any."""
    split = metrics.split
    estimated = np.isfinite(estimates.R_m2c).all(axis=(1, 2))
    if not estimated.any():
        return None
    confidence, score, judged = estimates.confidence[estimated], estimates.score[estimated], errors.select(estimated)
    calibrated = len(thresholds_deg) == 1 and None not in thresholds_deg and np.isfinite(confidence).all()
    threshold = next(iter(thresholds_deg)) if calibrated else DEFAULT_THRESHOLD_DEG
    R_true = np.stack([inst.R_m2c for inst in split.instances])[estimated]
    errors_deg = rotation_errors_deg(estimates.R_m2c[estimated], R_true, judged.obj_id, split.models_info)
    return evaluate_confidence(
        confidence if calibrated else score, calibrated, errors_deg, threshold,
        lambda mask: metric_scores(judged.select(mask), metrics.diameters_mm, metrics.thresholds)["MSSD"])


def _shared_split(methods: Sequence[Method | ResultsMethod], split: EvalSplit,
                  obj_ids: Iterable[int] | None) -> EvalSplit:
    """The instances every method can estimate, so that all rows of a table score the same instances.

    With ``obj_ids`` every method must know each of them; without, objects some
    method lacks are left out with a warning. A results file answers for every
    object: an instance it has no estimate of is wrong, as the BOP toolkit scores it.
    """
    models = [method for method in methods if isinstance(method, Method)]
    known = [method.known_objects() for method in models]
    if obj_ids is not None:
        wanted = set(obj_ids)
        for method, objects in zip(models, known, strict=True):
            lacking = sorted(wanted - objects)
            if lacking:
                raise PopcodeError(f"method {method.name!r} has no model for objects {lacking} "
                                   f"(its models know {sorted(objects)})")
    shared = set(split.obj_ids).intersection(*known)
    if not shared:
        raise PopcodeError(f"no object of the split ({split.obj_ids}) is known to every model: "
                           + "; ".join(f"{m.name!r} knows {sorted(o)}" for m, o in zip(models, known, strict=True)))
    left_out = sorted(set(split.obj_ids) - shared)
    if left_out:
        warnings.warn(f"objects {left_out} of the split are not known to every model and are not evaluated",
                      stacklevel=3)
    return restrict_to_objects(split, shared)


def _placed_with_depth(methods: Sequence[Method | ResultsMethod], split: EvalSplit, refine: bool,
                       names: Collection[str] | None) -> set[str]:
    """The names of the methods to place with depth (``names``, default all of model files), each checked before
    the first prediction: the split has depth images, their models surface points, refinement its library."""
    unknown = sorted(set(names or ()) - {method.name for method in methods})
    if unknown:
        raise PopcodeError(f"depth_methods names {unknown}, which are not among the methods")
    require_depth(split)
    chosen = [m for m in methods if isinstance(m, Method) and (names is None or m.name in names)]
    for method in chosen:
        check_depth_models(method, split.obj_ids, refine)
    return {method.name for method in chosen}


def evaluate_models(methods: Sequence[Method | ResultsMethod], split: EvalSplit, thresholds: Thresholds | None = None,
                    vsd: bool | None = None, obj_ids: Iterable[int] | None = None,
                    progress: bool = True, translation: bool = False, top_k: int = 1, depth: bool = False,
                    refine: bool = False, depth_methods: Collection[str] | None = None) -> list[MethodResult]:
    """Every method on the same split instances, sharing object models and depth renderers.

    ``translation`` also fits each instance's translation to its box, as the
    runtime does, and scores the full 6-D poses (:class:`FullPose`). ``depth``
    (implies ``translation``) also places each instance of a model file with its
    image's depth, as the runtime does, and scores those 6-D poses too
    (:class:`DepthPoses`); ``refine`` adds the poses refined against the depth;
    ``depth_methods`` names the methods placed with depth (default: all).
    ``top_k`` (1 to the runtime's ``MAX_TOP_K``) above 1 also scores the best of
    each population code's top-k hypotheses (:class:`BestOfTopK`; None for other
    methods), and refinement starts from those hypotheses.
    """
    top_k = integer(top_k, "top_k", 1, MAX_TOP_K)
    if not methods:
        raise PopcodeError("no models to evaluate")
    if refine and not depth:
        raise PopcodeError("refine refines each pose against its image's depth: ask for depth too")
    # Every model's object points before the first prediction: a model without them fails now, not after hours.
    points_mm = [method.object_points() if translation or depth else None for method in methods]
    shared = _shared_split(methods, split, obj_ids)
    with_depth = _placed_with_depth(methods, shared, refine, depth_methods) if depth else set()
    metrics = SplitMetrics(shared, thresholds, vsd)
    try:
        return [evaluate_model(method, metrics, progress, points, top_k,
                               depth_modes(refine) if method.name in with_depth else ())
                for method, points in zip(methods, points_mm, strict=True)]
    finally:
        metrics.close()
