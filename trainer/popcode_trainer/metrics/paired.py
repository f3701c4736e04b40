"""Two scores of the same instances compared: each instance's MSSD score and the paired difference of two
methods or looks with a bootstrap interval, so a difference is read against the noise of the instances drawn."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

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
    draws = np.random.default_rng(seed).integers(len(first), size=(BOOTSTRAP_DRAWS, len(first)))
    differences = second[draws].mean(axis=1) - first[draws].mean(axis=1)
    low, high = np.percentile(differences, [2.5, 97.5])
    return PairedDifference(len(first), float(first.mean()), float(second.mean()),
                            float(second.mean() - first.mean()), (float(low), float(high)))
