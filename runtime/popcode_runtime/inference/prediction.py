"""What ``PoseEstimator.predict`` returns: a ``Prediction`` per box, and the seconds of each stage (``Timings``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..coding.hypotheses import Hypothesis
from ..depth.surface_fit import TranslationSource


@dataclass(frozen=True)
class Prediction:
    """The rotation of one object instance (model-to-camera, OpenCV camera frame), and its translation when asked.

    With ``refine_depth`` the rotation is the one refined against the depth
    (``t_source`` ``refined``); ``score``, ``confidence`` and ``hypotheses``
    stay those of the code.
    """

    R_m2c: np.ndarray  # (3, 3)
    axis: np.ndarray  # (3,) unit rotation axis of R_m2c
    angle_rad: float  # rotation angle of R_m2c in [0, pi]
    score: float  # peak activation (population code) or the representation's own score
    box: tuple[float, float, float, float]
    obj_id: int | None  # None when a model of several objects was not told which
    code: np.ndarray | None = None  # raw network output, when asked for
    t_m2c_mm: np.ndarray | None = None  # (3,) translation, when asked for (from the box, or from depth when given)
    hypotheses: list[Hypothesis] | None = None  # every distinct pose, strongest first, when top_k > 1
    confidence: float | None = None  # P(rotation error < the model's threshold); None without a calibrator
    t_source: TranslationSource | None = None  # where t_m2c_mm came from; None without a translation
    depth_fit: float | None = None  # share of the visible surface the depth confirms less the share it sees through
    depth_note: str | None = None  # why the depth was not (fully) used for this instance; None when it was

    def to_dict(self) -> dict:
        data = {
            "box": list(self.box),
            "obj_id": self.obj_id,
            "R_m2c": self.R_m2c.tolist(),
            "axis": self.axis.tolist(),
            "angle_deg": float(np.degrees(self.angle_rad)),
            "score": self.score,
            "confidence": self.confidence,
        }
        if self.t_m2c_mm is not None:
            data["t_m2c_mm"] = self.t_m2c_mm.tolist()
            data["t_source"] = None if self.t_source is None else str(self.t_source)
        if self.depth_fit is not None:
            data["depth_fit"] = self.depth_fit
        if self.depth_note is not None:
            data["depth_note"] = self.depth_note
        if self.hypotheses is not None:
            data["hypotheses"] = [
                {"R_m2c": h.R_m2c.tolist(), "activation": h.activation, "score": h.score,
                 "equivalent": h.equivalent.tolist()}
                for h in self.hypotheses
            ]
        if self.code is not None:
            data["code"] = self.code.tolist()
        return data


@dataclass(frozen=True)
class Timings:
    """Seconds spent per stage of a call; the calls' chunks add up."""

    crop_s: float = 0.0
    inference_s: float = 0.0
    decode_s: float = 0.0  # decoding, frame conversion and the translation from the box
    depth_s: float = 0.0  # the translation from depth and the refinement

    def __add__(self, other: Timings) -> Timings:
        return Timings(self.crop_s + other.crop_s, self.inference_s + other.inference_s,
                       self.decode_s + other.decode_s, self.depth_s + other.depth_s)
