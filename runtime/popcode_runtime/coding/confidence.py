"""A calibrated confidence per estimate: the probability that its rotation error is below a threshold.

A population code says how sure the network is: a tall, sharp peak with no
rival elsewhere is usually right; a low peak, or mass spread over a second
pose that is *not* a symmetric equivalent of the first, is often wrong.
:func:`code_features` measures that on each code, and a :class:`Calibrator`
(a logistic model with non-negative weights, so confidence never falls when a
feature improves) maps the features to a probability. The trainer fits it at
export on held-out validation crops and stores it in the model's metadata;
this module only applies it, with numpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..base.checks import mapping, number
from ..base.errors import PopcodeError
from ..geometry.rotations import matrix_to_axis_angle
from .population_code import CodeLayout, PopulationCode, check_code

FEATURES = ("peak", "margin", "concentration")
DEFAULT_THRESHOLD_DEG = 10.0
RIVAL_RADIUS_SIGMAS = 2.5  # in code space, neurons further than this from every equivalent peak are rival poses
# A fitted weight or bias is a few units (features lie in [0, 1] or so); beyond this, exp() overflows and every
# confidence is 0 or 1: a corrupt calibrator, refused when the model loads.
MAX_LOGIT_TERM = 1000.0
NEAR_POSE_BUDGET = 1 << 22  # float32 distances held at once (16 MiB), whatever the batch and the symmetries


@dataclass(frozen=True)
class Calibrator:
    """``P(rotation error up to symmetry < threshold_deg) = sigmoid(bias + weights . features)``.

    ``weights`` (one per name in :data:`FEATURES`) are non-negative: the
    confidence is monotone in every feature. They are fitted for the argmax
    decoder; ``refined`` holds ``(weights, bias)`` fitted for the refined
    decoder, whose estimates are right more often from the same code (None:
    the argmax fit serves both). ``rival_radius_deg`` is the radius
    :func:`code_features` used when the calibrator was fitted; it must be the
    same at run time. ``fitted_on`` says what it was fitted on (for people).
    """

    threshold_deg: float
    rival_radius_deg: float
    weights: tuple[float, ...]
    bias: float
    fitted_on: dict[str, Any] = field(default_factory=dict)
    refined: tuple[tuple[float, ...], float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "threshold_deg", number(self.threshold_deg, "confidence threshold_deg", 0.0, 180.0))
        object.__setattr__(self, "rival_radius_deg",
                           number(self.rival_radius_deg, "confidence rival_radius_deg", 0.0, 180.0))
        object.__setattr__(self, "bias", number(self.bias, "confidence bias", -MAX_LOGIT_TERM, MAX_LOGIT_TERM))
        object.__setattr__(self, "weights", _weights(self.weights, "confidence"))
        if self.refined is not None:
            if isinstance(self.refined, (str, bytes)) or not isinstance(self.refined, Sequence) \
                    or len(self.refined) != 2:
                raise PopcodeError(f"confidence refined must be (weights, bias), got {self.refined!r}")
            object.__setattr__(self, "refined", (_weights(self.refined[0], "confidence refined"),
                                                 number(self.refined[1], "confidence refined bias",
                                                        -MAX_LOGIT_TERM, MAX_LOGIT_TERM)))
        mapping(self.fitted_on, "confidence fitted_on")
        if self.threshold_deg == 0.0 or self.rival_radius_deg == 0.0:
            raise PopcodeError("confidence threshold_deg and rival_radius_deg must be positive")

    def probability(self, features: np.ndarray, decoder: str = "argmax") -> np.ndarray:
        """Confidence ``(N,)`` in [0, 1] for features ``(N, len(FEATURES))`` of codes decoded by ``decoder``."""
        weights, bias = self.refined if decoder == "refined" and self.refined else (self.weights, self.bias)
        logits = bias + np.asarray(features, np.float64) @ np.asarray(weights)
        return 0.5 * (1.0 + np.tanh(0.5 * logits))  # the logistic function, without overflow warnings

    def to_dict(self) -> dict[str, Any]:
        data = {"threshold_deg": self.threshold_deg, "rival_radius_deg": self.rival_radius_deg,
                "features": list(FEATURES), "weights": list(self.weights), "bias": self.bias,
                "fitted_on": dict(self.fitted_on)}
        if self.refined is not None:
            data["refined"] = {"weights": list(self.refined[0]), "bias": self.refined[1]}
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Calibrator:
        data = mapping(data, "model metadata 'popcode.confidence'")
        if data.get("features") != list(FEATURES):
            raise PopcodeError(f"model metadata 'popcode.confidence' uses features {data.get('features')!r}; "
                               f"this runtime computes {list(FEATURES)}")
        missing = [key for key in ("threshold_deg", "rival_radius_deg", "weights", "bias") if key not in data]
        if missing:
            raise PopcodeError(f"model metadata 'popcode.confidence' lacks {', '.join(missing)}")
        refined = data.get("refined")
        if refined is not None:
            refined = mapping(refined, "model metadata 'popcode.confidence' refined")
            if "weights" not in refined or "bias" not in refined:
                raise PopcodeError("model metadata 'popcode.confidence' refined needs weights and bias")
            refined = (refined["weights"], refined["bias"])
        fitted_on = mapping(data.get("fitted_on", {}), "model metadata 'popcode.confidence' fitted_on")
        return cls(data["threshold_deg"], data["rival_radius_deg"], data["weights"], data["bias"], dict(fitted_on),
                   refined)


def _weights(values: Any, what: str) -> tuple[float, ...]:
    """One non-negative number per feature (the confidence never falls when a feature improves)."""
    if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or len(values) != len(FEATURES):
        raise PopcodeError(f"{what} weights must be {len(FEATURES)} numbers ({', '.join(FEATURES)}), got {values!r}")
    return tuple(number(w, f"{what} weight of {name}", 0.0, MAX_LOGIT_TERM)
                 for w, name in zip(values, FEATURES, strict=True))


def default_rival_radius_deg(layout: CodeLayout) -> float:
    """Where a peak's own blob ends: ``RIVAL_RADIUS_SIGMAS`` tuning widths, at least two lattice steps."""
    return float(max(RIVAL_RADIUS_SIGMAS * layout.sigma_deg, 2.0 * math.degrees(layout.axis_spacing_rad)))


def code_features(layout: CodeLayout, codes: np.ndarray, symmetries: np.ndarray,
                  rival_radius_deg: float) -> np.ndarray:
    """Features ``(N, 3)`` of codes ``(N, D)``, in the order of :data:`FEATURES`.

    ``symmetries`` ``(K, 3, 3)`` are the object's discrete symmetry rotations
    (identity included). A neuron belongs to the winning pose when it lies
    within ``rival_radius_deg`` of the argmax neuron's pose, or of one of its
    symmetric equivalents or axis/angle twins, in the code's own geometry
    (``sqrt(dtheta^2 + dphi^2)``, where the encoder puts its Gaussians; on the
    sphere for axis-only codes).

    - ``peak``: the argmax activation;
    - ``margin``: the peak minus the strongest neuron of any other pose;
    - ``concentration``: the share of the positive activation that sits on the winning pose.
    """
    codes = check_code(codes, layout.size).astype(np.float32, copy=False)
    symmetries = np.asarray(symmetries, np.float64)
    features = np.empty((len(codes), len(FEATURES)))
    if not len(codes):
        return features
    radius = math.radians(rival_radius_deg)
    winners = PopulationCode(layout).preferred_rotations(np.argmax(codes, axis=1))
    per_chunk = max(1, NEAR_POSE_BUDGET // (2 * len(symmetries) * layout.size))  # bounds the distance array
    for start in range(0, len(codes), per_chunk):
        chunk = slice(start, start + per_chunk)
        part = codes[chunk]
        near = _near_poses(layout, winners[chunk, None] @ symmetries[None], radius)
        top = part.max(axis=1)
        rival = np.where(near, -np.inf, part).max(axis=1)
        positive = np.maximum(part, 0.0)
        total = positive.sum(axis=1)
        features[chunk, 0] = top
        features[chunk, 1] = np.where(np.isfinite(rival), top - rival, top)
        features[chunk, 2] = np.divide((positive * near).sum(axis=1), total, out=np.zeros(len(part)),
                                       where=total > 0)
    return features


def _near_poses(layout: CodeLayout, equivalents: np.ndarray, radius_rad: float) -> np.ndarray:
    """``(N, D)`` bool: the neurons within ``radius_rad`` of any of each code's rotations ``(N, K, 3, 3)``."""
    count, k = equivalents.shape[:2]
    if layout.axis_only:
        directions = equivalents @ np.asarray(layout.symmetry_axis)  # (N, K, 3)
        return (directions @ layout.axes.T).max(axis=1) >= math.cos(radius_rad)
    axes, angles = matrix_to_axis_angle(equivalents.reshape(-1, 3, 3))
    axes, angles = axes.reshape(count, k, 3), angles.reshape(count, k)
    axes = np.concatenate([axes, -axes], axis=1)  # each rotation sits in the code twice: (r, phi), (-r, 2 pi - phi)
    angles = np.concatenate([angles, 2.0 * np.pi - angles], axis=1)
    dtheta2 = (np.arccos(np.clip(axes @ layout.axes.T, -1.0, 1.0)) ** 2).astype(np.float32)  # (N, 2K, n_axes)
    dphi2 = (np.angle(np.exp(1j * (angles[..., None] - layout.angles_rad))) ** 2).astype(np.float32)  # (N, 2K, m)
    distance2 = dtheta2[..., None] + dphi2[:, :, None, :]  # (N, 2K, n_axes, m)
    return (distance2.min(axis=1) < radius_rad**2).reshape(count, -1)
