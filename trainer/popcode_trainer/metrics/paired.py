"""Two scores of the same instances compared: each instance's MSSD score and the paired difference of two
methods or looks with a bootstrap interval, so a difference is read against the noise of the instances drawn."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.stats import bootstrap

from .recall import Thresholds

BOOTSTRAP_DRAWS = 2000


@dataclass(frozen=True)
class PairedDifference:
    """Mean of ``second - first`` over the instances, in the scores' unit, and its bootstrap 95 % interval."""

    instances: int
    first: float
    second: float
    difference: float
    interval: tuple[float, float]

    def to_dict(self) -> dict[str, Any]:
        return {"instances": self.instances, "first": self.first, "second": self.second,
                "difference": self.difference, "interval": list(self.interval)}


def instance_mssd_scores(mssd_mm: np.ndarray, obj_ids: np.ndarray, diameters_mm: Mapping[int, float],
                         thresholds: Thresholds | None = None) -> np.ndarray:
    """Each instance's share of BOP's MSSD thresholds its error is below: their mean is the MSSD recall."""
    fractions = np.asarray((thresholds or Thresholds()).mssd_fractions)
    diameter = np.array([float(diameters_mm[int(obj_id)]) for obj_id in obj_ids])
    return (np.asarray(mssd_mm, np.float64)[:, None] / diameter[:, None] < fractions[None, :]).mean(axis=1)


def paired_difference(first: np.ndarray, second: np.ndarray, seed: int = 0) -> PairedDifference:
    """``second`` against ``first``, scores of the same instances in the same order."""
    first, second = np.asarray(first, np.float64), np.asarray(second, np.float64)
    if first.shape != second.shape or first.ndim != 1 or not len(first):
        raise ValueError(f"paired scores need two equal, non-empty 1-D arrays, got {first.shape} and {second.shape}")
    difference = float(second.mean() - first.mean())
    interval = (difference, difference)  # one instance: no spread to draw from (scipy needs two)
    if len(first) > 1:
        # the percentile interval of the mean difference over instances drawn with replacement, both methods' scores
        # of an instance drawn together
        drawn = bootstrap((first, second), _mean_difference, paired=True, vectorized=True,
                          n_resamples=BOOTSTRAP_DRAWS, confidence_level=0.95, method="percentile",
                          random_state=np.random.default_rng(seed)).confidence_interval
        interval = (float(drawn.low), float(drawn.high))
    return PairedDifference(len(first), float(first.mean()), float(second.mean()), difference, interval)


def _mean_difference(first: np.ndarray, second: np.ndarray, axis: int = -1) -> np.ndarray:
    return second.mean(axis=axis) - first.mean(axis=axis)
