"""What a method says about each instance of a split: the common result of running models and reading results files."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Estimates:
    """A method's rotations of a split's instances, with what it says about each."""

    R_m2c: np.ndarray  # (N, 3, 3)
    confidence: np.ndarray  # (N,) calibrated P(error < threshold); NaN where the model has no calibrator
    score: np.ndarray  # (N,) the representation's raw score (peak activation, ...)
    seconds_per_crop: float  # crop + network + decoding
    hypotheses: np.ndarray | None = None  # (K, N, 3, 3) candidate rotations by rank: R_m2c, then the code's
    # other distinct poses, strongest first, each instance's list padded with R_m2c; None: no hypotheses asked for
