"""Is a confidence worth acting on? Calibration (ECE, reliability) and usefulness (AUROC, accuracy at coverage).

An estimate is *correct* when its rotation error up to the object's symmetries
is below the calibrator's threshold; a calibrated confidence of 0.8 should be
right 80 % of the time (expected calibration error, ECE), and ranking estimates
by it should put the wrong ones last (AUROC; the MSSD of the estimates a robot
keeps when it acts on the most confident fractions, :data:`COVERAGES`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import rankdata

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.symmetries import (
    SymmetryClass,
    continuous_axis,
    rotation_error_up_to_symmetry,
    symmetry_class,
    symmetry_rotations,
)

ECE_BINS = 10
COVERAGES = (1.0, 0.9, 0.75, 0.5)


def rotation_errors_deg(R_est: np.ndarray, R_true: np.ndarray, obj_ids: np.ndarray,
                        models_info: Mapping[int, Mapping[str, Any]],
                        equivalent: Mapping[int, np.ndarray] | None = None) -> np.ndarray:
    """Rotation error ``(N,)`` [deg] up to each object's symmetries (continuous ones: the axis angle); ``equivalent``
    (object -> rotations ``(K, 3, 3)``, e.g. ``near_symmetry.look_alike_rotations``) replaces an object's declared
    discrete symmetries."""
    errors = np.empty(len(obj_ids))
    for obj_id in np.unique(obj_ids):
        rows = np.flatnonzero(obj_ids == obj_id)
        info = models_info[int(obj_id)]
        axis = continuous_axis(info) if symmetry_class(info) is SymmetryClass.CONTINUOUS else None
        symmetries = equivalent[int(obj_id)] if equivalent and int(obj_id) in equivalent else symmetry_rotations(info)
        errors[rows] = rotation_error_up_to_symmetry(np.asarray(R_est)[rows], np.asarray(R_true)[rows],
                                                     symmetries, axis)
    return np.degrees(errors)


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray,
                               bins: int = ECE_BINS) -> tuple[float, list[dict[str, float]]]:
    """ECE over equal-width confidence bins, and the bins (the reliability diagram's points)."""
    confidence, correct = np.asarray(confidence, np.float64), np.asarray(correct, bool)
    index = np.minimum((confidence * bins).astype(int), bins - 1)
    rows, ece = [], 0.0
    for b in range(bins):
        chosen = index == b
        if not chosen.any():
            continue
        mean_confidence, accuracy = float(confidence[chosen].mean()), float(correct[chosen].mean())
        ece += chosen.mean() * abs(mean_confidence - accuracy)
        rows.append({"low": b / bins, "high": (b + 1) / bins, "count": int(chosen.sum()),
                     "confidence": mean_confidence, "accuracy": accuracy})
    return float(ece), rows


def auroc(score: np.ndarray, correct: np.ndarray) -> float:
    """Probability that a correct estimate scores above a wrong one (ties count half); NaN without both kinds."""
    score, correct = np.asarray(score, np.float64), np.asarray(correct, bool)
    positives, negatives = int(correct.sum()), int((~correct).sum())
    if positives == 0 or negatives == 0:
        return float("nan")
    ranks = rankdata(score)  # tied scores share their average rank (Mann-Whitney U)
    u = ranks[correct].sum() - positives * (positives + 1) / 2.0
    return float(u / (positives * negatives))


def most_confident(score: np.ndarray, coverage: float) -> np.ndarray:
    """Boolean mask of the ``coverage`` share of estimates with the highest score (ties broken by order)."""
    if not 0.0 < coverage <= 1.0:
        raise PopcodeError(f"coverage must lie in (0, 1], got {coverage}")
    keep = max(1, int(round(coverage * len(score))))
    mask = np.zeros(len(score), bool)
    mask[np.argsort(-np.asarray(score, np.float64), kind="stable")[:keep]] = True
    return mask


@dataclass(frozen=True)
class ConfidenceEvaluation:
    """How well a method's per-estimate score predicts a rotation error below ``threshold_deg``."""

    kind: str  # "calibrated confidence", or the raw score of a model without a calibrator
    threshold_deg: float
    accuracy: float  # share of estimates below the threshold
    ece: float | None  # None when the score is not a probability
    reliability: list[dict[str, float]]
    auroc: float
    mssd_at_coverage: dict[float, float]  # coverage -> MSSD recall of the most confident estimates

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "threshold_deg": self.threshold_deg, "accuracy": self.accuracy, "ece": self.ece,
                "reliability": self.reliability, "auroc": self.auroc,
                "mssd_at_coverage": {str(k): v for k, v in self.mssd_at_coverage.items()}}


def evaluate_confidence(score: np.ndarray, probability: bool, errors_deg: np.ndarray, threshold_deg: float,
                        mssd_of) -> ConfidenceEvaluation:
    """Calibration (if ``probability``) and usefulness of ``score`` against ``errors_deg``.

    ``mssd_of(mask)`` is the MSSD recall of the estimates in ``mask``.
    """
    correct = np.asarray(errors_deg) < threshold_deg
    ece, reliability = expected_calibration_error(score, correct) if probability else (None, [])
    return ConfidenceEvaluation(
        kind="calibrated confidence" if probability else "raw score",
        threshold_deg=float(threshold_deg), accuracy=float(correct.mean()), ece=ece, reliability=reliability,
        auroc=auroc(score, correct),
        mssd_at_coverage={c: float(mssd_of(most_confident(score, c))) for c in COVERAGES},
    )
