"""Fit a model's confidence calibrator at export, on validation images held out of its training.

The exported network runs through the runtime's one pipeline on each held-out
instance (crop -> network -> decode -> camera frame), its rotation error up to
symmetry is measured against the ground truth, and a logistic model with
non-negative weights is fitted from the code's features
(:func:`popcode_runtime.coding.confidence.code_features`) to "error < threshold".
The weights are constrained, not just fitted, to be non-negative so that a
taller, sharper, less contested peak can never lower the confidence.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.confidence import (
    DEFAULT_THRESHOLD_DEG,
    FEATURES,
    Calibrator,
    code_features,
    default_rival_radius_deg,
)
from popcode_runtime.geometry.symmetries import symmetry_rotations
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.inference.image_loop import estimate_images, group_by_image
from popcode_runtime.model.metadata import GRID_REPRESENTATIONS, Representation

from ..data.bop import Instance
from ..metrics.confidence import rotation_errors_deg
from ..train.training_data import TrainingSplit, read_training_split
from .model_io import TrainedModel
from .torch_engine import trained_estimator

MAX_CALIBRATION_INSTANCES = 2000  # enough for four weights; bounds the export's time
MIN_PER_OUTCOME = 5  # correct and wrong estimates each; fewer cannot say where the boundary lies
L2_PENALTY = 1e-3  # keeps the weights finite when the classes separate perfectly


@dataclass(frozen=True)
class HeldOutEstimates:
    """What the model says about held-out instances and how wrong it is, per decoder."""

    features: np.ndarray  # (N, len(FEATURES)), of the code (the same whatever the decoder)
    errors_deg: dict[str, np.ndarray]  # decoder -> (N,) rotation error up to symmetry


def held_out_instances(held_out: list[Instance], seed: int, limit: int = MAX_CALIBRATION_INSTANCES) -> list[Instance]:
    """At most ``limit`` of the instances training held out, chosen with the training seed."""
    if len(held_out) > limit:
        chosen = np.random.default_rng(seed).choice(len(held_out), limit, replace=False)
        held_out = [held_out[i] for i in sorted(chosen)]
    return held_out


def estimate_held_out(estimators: Sequence[PoseEstimator], instances: Sequence[Instance], rival_radius_deg: float,
                      progress: bool = True) -> HeldOutEstimates:
    """Run the estimators (one model, one per decoder) on every instance, each through the runtime's per-image
    loop; the code's features (from the first) and each decoder's errors up to symmetry."""
    meta = estimators[0].metadata
    images = group_by_image(instances)
    codes = np.empty((len(instances), meta.output_dim), np.float32)
    R_est = {estimator.decoder: np.empty((len(instances), 3, 3)) for estimator in estimators}
    for index, estimator in enumerate(estimators):
        for done in tqdm(estimate_images([estimator], [estimator.decoder], images, return_code=index == 0),
                         total=len(images), unit="img", disable=not progress,
                         desc=f"confidence: held-out crops ({estimator.decoder})"):
            rows = list(done.key)
            R_est[estimator.decoder][rows] = np.stack([p.R_m2c for p in done.predictions])
            if index == 0:
                codes[rows] = np.stack([p.code for p in done.predictions])
    obj_ids = np.array([inst.obj_id for inst in instances])
    features = np.empty((len(instances), len(FEATURES)))
    for obj_id in np.unique(obj_ids):
        rows = np.flatnonzero(obj_ids == obj_id)
        features[rows] = code_features(meta.code, codes[rows], symmetry_rotations(meta.objects[int(obj_id)]),
                                       rival_radius_deg)
    R_true = np.stack([inst.R_m2c for inst in instances])
    return HeldOutEstimates(features, {decoder: rotation_errors_deg(R, R_true, obj_ids, meta.objects)
                                       for decoder, R in R_est.items()})


def fit_logistic(features: np.ndarray, correct: np.ndarray) -> tuple[np.ndarray, float]:
    """Weights ``>= 0`` and bias of ``P(correct) = sigmoid(bias + w . features)`` (maximum likelihood, small L2).

    Features are standardised for the fit and the weights mapped back, which
    keeps their signs.
    """
    mean, scale = features.mean(axis=0), features.std(axis=0)
    scale = np.where(scale > 1e-12, scale, 1.0)
    x = (features - mean) / scale
    y = np.asarray(correct, np.float64)

    def loss(params: np.ndarray) -> tuple[float, np.ndarray]:
        logits = params[0] + x @ params[1:]
        p = 0.5 * (1.0 + np.tanh(0.5 * logits))
        nll = np.logaddexp(0.0, logits) - y * logits  # -log likelihood, stable for large |logits|
        residual = (p - y) / len(y)
        grad = np.concatenate([[residual.sum()], x.T @ residual + 2 * L2_PENALTY * params[1:]])
        return float(nll.mean() + L2_PENALTY * params[1:] @ params[1:]), grad

    bounds = [(None, None)] + [(0.0, None)] * x.shape[1]
    result = minimize(loss, np.zeros(x.shape[1] + 1), jac=True, method="L-BFGS-B", bounds=bounds)
    weights = result.x[1:] / scale
    return weights, float(result.x[0] - weights @ mean)


def fit_calibrator(estimator: PoseEstimator, instances: Sequence[Instance],
                   threshold_deg: float = DEFAULT_THRESHOLD_DEG,
                   progress: bool = True) -> tuple[Calibrator | None, str]:
    """A calibrator for the estimator's model, or None and the reason there is none."""
    meta = estimator.metadata
    if not 0.0 < threshold_deg < 180.0:
        raise PopcodeError(f"the confidence threshold must lie in (0, 180) degrees, got {threshold_deg:g}")
    if meta.representation not in GRID_REPRESENTATIONS:
        return None, f"a {meta.representation} model has no code to read a confidence from"
    if not instances:
        return None, "no held-out images (set data.val_fraction above 0 to keep some out of training)"
    radius = default_rival_radius_deg(meta.code)
    estimators = [estimator]
    if meta.representation == Representation.POPULATION_CODE:  # the same codes, decoded between the neurons too
        estimators.append(PoseEstimator.from_engine(estimator.engine, meta, decoder="refined"))
    held_out = estimate_held_out(estimators, instances, radius, progress)
    correct = held_out.errors_deg[estimator.decoder] < threshold_deg
    if min(correct.sum(), (~correct).sum()) < MIN_PER_OUTCOME:
        return None, (f"{int(correct.sum())} of {len(correct)} held-out estimates are within {threshold_deg:g} deg: "
                      f"at least {MIN_PER_OUTCOME} right and {MIN_PER_OUTCOME} wrong ones are needed to calibrate")
    weights, bias = fit_logistic(held_out.features, correct)
    refined = None
    if "refined" in held_out.errors_deg:
        refined_correct = held_out.errors_deg["refined"] < threshold_deg
        if min(refined_correct.sum(), (~refined_correct).sum()) >= MIN_PER_OUTCOME:
            refined_weights, refined_bias = fit_logistic(held_out.features, refined_correct)
            refined = (tuple(float(w) for w in refined_weights), refined_bias)
    fitted_on = {"held_out_instances": len(correct), "share_correct": round(float(correct.mean()), 4)}
    return Calibrator(threshold_deg, radius, tuple(float(w) for w in weights), bias, fitted_on, refined), \
        f"fitted on {len(correct)} held-out crops ({100 * correct.mean():.1f} % within {threshold_deg:g} deg)"


def calibrate_checkpoint(trained: TrainedModel, threshold_deg: float = DEFAULT_THRESHOLD_DEG,
                         progress: bool = True, split: TrainingSplit | None = None) -> tuple[Calibrator | None, str]:
    """Fit the calibrator of a loaded training checkpoint on the images its training held out (``split``: its
    training splits, already read; see :func:`fit_calibrator`)."""
    estimator = trained_estimator(trained)
    if estimator.metadata.representation not in GRID_REPRESENTATIONS:
        return fit_calibrator(estimator, [], threshold_deg, progress)
    config = trained.config
    if not config.data.splits or not config.data.models_dir:
        return None, "the checkpoint's config names no BOP split whose held-out images could calibrate it"
    split = split or read_training_split(config)
    return fit_calibrator(estimator, held_out_instances(split.val, config.train.seed), threshold_deg, progress)
