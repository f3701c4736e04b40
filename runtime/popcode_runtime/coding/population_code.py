"""The neural population code of a rotation (docs/design.md#population-code; paper section III-A).

Neurons sit on the direct product of a Fibonacci sphere of ``n`` preferred
axes and a circle of ``m`` preferred angles; neuron ``k = i * m + j`` prefers
axis ``u_i`` and angle ``phi_j``. Its activation for a rotation with axis ``r``
and angle ``phi`` is ``exp(-(dtheta^2 + dphi^2) / (2 sigma^2))``. Because the
Gaussian factorises into an axis part and an angle part, a target is a sum of
outer products, which keeps encoding fast enough to run on the fly.

Objects with a continuous symmetry use the axis-only variant: ``n`` neurons
encoding the direction of the symmetry axis in the camera frame.
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

import numpy as np

from ..base.checks import flag, integer, mapping, number, number_array
from ..base.errors import PopcodeError
from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rotation_between

PAPER_N_AXES = 2562
PAPER_N_ANGLES = 36
PAPER_SIGMA_DEG = 20.0
# Bounds on a layout read from a model file: the lattice neighbour search is O(n_axes^2) and a
# decoded batch holds N x size floats, so absurd sizes must stop at the metadata, not in numpy.
MAX_AXES = 16384
MAX_ANGLES = 720
MAX_CODE_SIZE = 1 << 21


def fibonacci_lattice(n: int) -> np.ndarray:
    """``n`` near-uniform unit vectors ``(n, 3)``: ``z_i = 1 - (2i+1)/n``, golden-angle azimuth."""
    if n < 1:
        raise PopcodeError(f"a lattice needs at least one axis, got n={n}")
    i = np.arange(n, dtype=np.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    rho = np.sqrt(np.clip(1.0 - z * z, 0.0, None))
    psi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([rho * np.cos(psi), rho * np.sin(psi), z], axis=-1)


def _wrapped_angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Absolute angular distance on the circle, in [0, pi]."""
    d = np.mod(a - b + np.pi, 2.0 * np.pi) - np.pi
    return np.abs(d)


@dataclass(frozen=True)
class CodeLayout:
    """Shape and tuning of a population code; stored in every model's metadata.

    ``symmetry_axis`` (model frame) is required for, and only used by, the
    axis-only variant.
    """

    n_axes: int = PAPER_N_AXES
    n_angles: int = PAPER_N_ANGLES
    sigma_deg: float = PAPER_SIGMA_DEG
    axis_only: bool = False
    symmetry_axis: tuple[float, float, float] | None = None
    lattice: str = "fibonacci"

    def __post_init__(self) -> None:
        if self.lattice != "fibonacci":
            raise PopcodeError(f"unknown lattice {self.lattice!r}; only 'fibonacci' is defined")
        axis_only = flag(self.axis_only, "code.axis_only")
        n_axes = integer(self.n_axes, "code.n_axes", 1, MAX_AXES)
        n_angles = integer(self.n_angles, "code.n_angles", 0 if axis_only else 1, MAX_ANGLES)
        sigma = number(self.sigma_deg, "code.sigma_deg")
        if not 0.0 < sigma < 180.0:
            raise PopcodeError(f"code.sigma_deg must lie in (0, 180), got {sigma:g}")
        if not axis_only and n_axes * n_angles > MAX_CODE_SIZE:
            raise PopcodeError(f"code of {n_axes} x {n_angles} neurons exceeds the runtime's limit of "
                               f"{MAX_CODE_SIZE} neurons")
        for name, value in (("axis_only", axis_only), ("n_axes", n_axes), ("n_angles", n_angles),
                            ("sigma_deg", sigma)):
            object.__setattr__(self, name, value)
        if axis_only:
            if self.symmetry_axis is None:
                raise PopcodeError("an axis-only code needs the object's symmetry_axis")
            axis = number_array(self.symmetry_axis, "code.symmetry_axis", (3,))
            if np.linalg.norm(axis) < 1e-9:
                raise PopcodeError(f"code.symmetry_axis must not be zero: {self.symmetry_axis}")
            object.__setattr__(self, "symmetry_axis", tuple(float(v) for v in axis / np.linalg.norm(axis)))

    @property
    def digest(self) -> str:
        """A checksum of what fixes each neuron's meaning (lattice, n, m, sigma).

        Written into the metadata at export, so a layout relabelled by hand
        (642 x 36 as 1284 x 18: same width, other neurons) is caught at load.
        """
        n_angles = 0 if self.axis_only else self.n_angles
        text = f"{self.lattice}|{self.n_axes}|{n_angles}|{self.axis_only}|{self.sigma_deg!r}"
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    @property
    def size(self) -> int:
        """Number of neurons (length of the output vector)."""
        return self.n_axes if self.axis_only else self.n_axes * self.n_angles

    @property
    def sigma_rad(self) -> float:
        return float(np.deg2rad(self.sigma_deg))

    @property
    def axis_spacing_rad(self) -> float:
        """Typical angle between neighbouring lattice axes, ``sqrt(4 pi / n)`` (each axis holds ``4 pi / n`` sr)."""
        return float(np.sqrt(4.0 * np.pi / self.n_axes))

    @cached_property
    def axes(self) -> np.ndarray:
        """Preferred axes ``(n_axes, 3)``."""
        return fibonacci_lattice(self.n_axes)

    @cached_property
    def angles_rad(self) -> np.ndarray:
        """Preferred angles ``(n_angles,)``: ``2 pi j / m``."""
        return 2.0 * np.pi * np.arange(self.n_angles) / self.n_angles

    def to_dict(self) -> dict[str, Any]:
        data = asdict(self)
        data["symmetry_axis"] = list(self.symmetry_axis) if self.symmetry_axis else None
        data["digest"] = self.digest
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> CodeLayout:
        """A layout from its :meth:`to_dict` form; a ``digest`` (absent in older models) must match."""
        data = mapping(data, "code")
        known = {"n_axes", "n_angles", "sigma_deg", "axis_only", "symmetry_axis", "lattice", "digest"}
        unknown = set(data) - known
        if unknown:
            raise PopcodeError(f"unknown code layout keys {sorted(unknown)}; expected {sorted(known)}")
        values = {key: value for key, value in data.items() if key != "digest"}
        layout = cls(**values)
        if "digest" in data and data["digest"] != layout.digest:
            raise PopcodeError(
                f"code layout checksum {data['digest']!r} does not match its values ({layout.n_axes} axes x "
                f"{layout.n_angles} angles, sigma {layout.sigma_deg:g}); the layout was edited after export"
            )
        return layout


@dataclass(frozen=True)
class DecodedRotations:
    """Rotations decoded from a batch of codes; every field has leading dimension N."""

    R: np.ndarray  # (N, 3, 3)
    axis: np.ndarray  # (N, 3) rotation axis of R
    angle_rad: np.ndarray  # (N,) rotation angle of R in [0, pi]
    neuron: np.ndarray  # (N,) index of the winning neuron
    activation: np.ndarray  # (N,) its activation (the score)


class PopulationCode:
    """Encoder and argmax decoder for one :class:`CodeLayout`."""

    def __init__(self, layout: CodeLayout) -> None:
        self.layout = layout
        self._axes = layout.axes
        self._angles = layout.angles_rad
        self._two_sigma_sq = 2.0 * layout.sigma_rad**2

    # -- encoding -------------------------------------------------------------
    def _axis_tuning(self, directions: np.ndarray, preferred: np.ndarray | None = None) -> np.ndarray:
        """Gaussian of the angle between ``directions (..., 3)`` and each preferred axis -> ``(..., n)``."""
        preferred = self._axes if preferred is None else preferred
        cos = np.clip(directions @ preferred.T, -1.0, 1.0)
        return np.exp(-np.arccos(cos) ** 2 / self._two_sigma_sq)

    def _angle_tuning(self, angles: np.ndarray, preferred: np.ndarray | None = None) -> np.ndarray:
        """Gaussian of the wrapped distance to each preferred angle -> ``(..., m)``."""
        preferred = self._angles if preferred is None else preferred
        diff = _wrapped_angle_diff(angles[..., None], preferred)
        return np.exp(-diff**2 / self._two_sigma_sq)

    def encode(self, R_m2c: np.ndarray, symmetries: np.ndarray | None = None,
               neurons: np.ndarray | None = None) -> np.ndarray:
        """Target codes ``(N, size)`` float32 for rotations ``(N, 3, 3)`` (or one ``(3, 3)``).

        ``symmetries`` are the object's symmetry rotations ``(K, 3, 3)`` with the
        identity included (see :func:`symmetries.symmetry_rotations`); default:
        none. Each equivalent rotation ``R S_k`` contributes its peak and the
        peak of its axis/angle twin ``(-r, 2 pi - phi)``; for the axis-only code
        each distinct direction ``R S_k a`` contributes one peak. ``neurons``
        (indices) restricts the output to those neurons, ``(N, len(neurons))``.
        """
        R = np.asarray(R_m2c, dtype=np.float64)
        single = R.ndim == 2
        R = R.reshape(-1, 3, 3)
        S = np.eye(3)[None] if symmetries is None else np.asarray(symmetries, dtype=np.float64).reshape(-1, 3, 3)
        selected = np.arange(self.layout.size) if neurons is None else np.asarray(neurons)
        encode = self._encode_axis_only if self.layout.axis_only else self._encode_full
        code = encode(R, S, selected).astype(np.float32)
        return code[0] if single else code

    def _encode_full(self, R: np.ndarray, S: np.ndarray, neurons: np.ndarray) -> np.ndarray:
        equivalent = R[:, None] @ S[None]  # (N, K, 3, 3)
        axis, angle = matrix_to_axis_angle(equivalent)
        axes = np.concatenate([axis, -axis], axis=1)  # (N, 2K, 3): the twin peaks
        angles = np.concatenate([angle, 2.0 * np.pi - angle], axis=1)
        if len(neurons) == self.layout.size:  # the whole code: a sum of outer products, one per peak
            axis_part = self._axis_tuning(axes).astype(np.float32).transpose(0, 2, 1)  # (N, n, 2K)
            code = axis_part @ self._angle_tuning(angles).astype(np.float32)  # batched BLAS, in the output's precision
            return code.reshape(len(R), -1)
        axis_index, angle_index = np.divmod(neurons, self.layout.n_angles)
        axis_part = self._axis_tuning(axes, self._axes[axis_index])
        angle_part = self._angle_tuning(angles, self._angles[angle_index])
        return np.sum(axis_part * angle_part, axis=1)

    def _encode_axis_only(self, R: np.ndarray, S: np.ndarray, neurons: np.ndarray) -> np.ndarray:
        a = np.asarray(self.layout.symmetry_axis)
        directions = _distinct_directions(S @ a)  # model frame, (D, 3)
        camera_dirs = np.einsum("bij,dj->bdi", R, directions)
        return self._axis_tuning(camera_dirs, self._axes[neurons]).sum(axis=1)

    # -- decoding -------------------------------------------------------------
    def decode(self, code: np.ndarray) -> DecodedRotations:
        """Argmax decoding (the paper's): the winning neuron's preferred rotation.

        Axis-only codes give the minimal rotation taking the symmetry axis to
        the winning axis; every rotation about that axis is equivalent.
        """
        code = check_code(code, self.layout.size)
        neuron = np.argmax(code, axis=1)
        activation = code[np.arange(len(code)), neuron]
        if self.layout.axis_only:
            R = rotation_between(np.asarray(self.layout.symmetry_axis), self._axes[neuron])
        else:
            axis = self._axes[neuron // self.layout.n_angles]
            R = axis_angle_to_matrix(axis, self._angles[neuron % self.layout.n_angles])
        axis, angle = matrix_to_axis_angle(R)
        return DecodedRotations(R=R, axis=axis, angle_rad=angle, neuron=neuron, activation=activation)

    def preferred_rotations(self, neurons: np.ndarray) -> np.ndarray:
        """Preferred rotation ``(..., 3, 3)`` of neuron indices (full code only)."""
        if self.layout.axis_only:
            return rotation_between(np.asarray(self.layout.symmetry_axis), self._axes[neurons])
        neurons = np.asarray(neurons)
        return axis_angle_to_matrix(self._axes[neurons // self.layout.n_angles],
                                    self._angles[neurons % self.layout.n_angles])


def _distinct_directions(directions: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Unique unit vectors among ``(D, 3)``, first occurrence kept, order preserved."""
    kept: list[np.ndarray] = []
    for d in directions:
        d = d / np.linalg.norm(d)
        if all(np.linalg.norm(d - k) > tol for k in kept):
            kept.append(d)
    return np.stack(kept)


def check_code(code: np.ndarray, size: int) -> np.ndarray:
    """Validate a batch of codes ``(N, size)`` (or one ``(size,)``) and return it 2-D.

    A code with NaN or inf, or a flat code with no peak, cannot name a rotation.
    """
    code = np.asarray(code)
    if code.ndim == 1:
        code = code[None]
    if code.ndim != 2 or code.shape[1] != size:
        raise PopcodeError(f"expected codes of shape (N, {size}), got {code.shape}")
    if not np.isfinite(code).all():
        bad = np.flatnonzero(~np.isfinite(code).all(axis=1)).tolist()
        raise PopcodeError(f"code contains NaN or inf (rows {bad[:10]}); the model output is unusable")
    return code
