"""What a method says about each instance of a split: the common result of running models and reading results files."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

UNKNOWN_TIME_S = -1.0  # BOP19's time of an image nobody timed


@dataclass(frozen=True)
class Estimates:
    """A method's rotations of a split's instances, with what it says about each."""

    R_m2c: np.ndarray  # (N, 3, 3)
    confidence: np.ndarray  # (N,) calibrated P(error < threshold); NaN where the model has no calibrator
    score: np.ndarray  # (N,) the representation's raw score (peak activation, ...)
    seconds_per_crop: float  # crop + network + decoding
    image_s: np.ndarray  # (N,) seconds of the method's work on the instance's image, for all of that image's
    # instances (the same on each of them: BOP19's time); UNKNOWN_TIME_S where not measured
    hypotheses: np.ndarray | None = None  # (K, N, 3, 3) candidate rotations by rank: R_m2c, then the code's
    # other distinct poses, strongest first, each instance's list padded with R_m2c; None: no hypotheses asked for

    def bop19_score(self) -> np.ndarray:
        """``(N,)``: the calibrated confidence where the model has a calibrator, else the raw score."""
        return np.where(np.isfinite(self.confidence), self.confidence, self.score)
