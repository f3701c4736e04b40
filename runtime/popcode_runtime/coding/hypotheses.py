"""Every distinct peak of a code as a scored rotation hypothesis.

A symmetric object's code has one peak per equivalent pose (and each pose
twice in axis/angle form). Non-maximum suppression in the code's own axis x
angle space (on the sphere for axis-only codes) over local maxima finds the
peaks; a peak whose rotation equals one already found is its axis/angle twin
and is dropped. With the object's symmetries, peaks that are the same pose are merged into one hypothesis that
lists its equivalent rotations. A robot planning a grasp can use them all.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..base.errors import PopcodeError
from ..geometry.rotations import geodesic_angle
from .population_code import CodeLayout, PopulationCode, check_code
from .refine import lattice_neighbours, refine_neuron

DEFAULT_MIN_RELATIVE = 0.2  # peaks below this share of the top activation are noise


@dataclass(frozen=True)
class Hypothesis:
    """One pose: its rotation, the peak's activation and its share of all hypotheses' activation."""

    R_m2c: np.ndarray  # (3, 3)
    activation: float
    score: float  # activation / sum of the hypotheses' activations, in (0, 1]
    equivalent: np.ndarray  # (E, 3, 3) merged peaks that are the same pose under the symmetry, R_m2c first


def _suppression_mask(layout: CodeLayout, neuron: int, radius_rad: float) -> np.ndarray:
    """Neurons within ``radius_rad`` of ``neuron`` in the code's own geometry.

    That is the axis x angle product space (``dtheta^2 + dphi^2``), where each
    peak is a Gaussian blob; suppressing by distance on SO(3) instead would
    leave the blob's far shoulders standing as false peaks.
    """
    if layout.axis_only:
        return layout.axes @ layout.axes[neuron] >= np.cos(radius_rad)
    axis_index, angle_index = divmod(neuron, layout.n_angles)
    dtheta = np.arccos(np.clip(layout.axes @ layout.axes[axis_index], -1.0, 1.0))
    dphi = np.abs(np.angle(np.exp(1j * (layout.angles_rad - layout.angles_rad[angle_index]))))
    return ((dtheta[:, None] ** 2 + dphi[None, :] ** 2) < radius_rad**2).reshape(-1)


def _is_local_maximum(layout: CodeLayout, code: np.ndarray, neuron: int) -> bool:
    """True if no lattice neighbour (and, for full codes, no angle neighbour) is higher."""
    if layout.axis_only:
        return bool(code[neuron] >= code[lattice_neighbours(layout.n_axes)[neuron]].max())
    m = layout.n_angles
    axis_index, angle_index = divmod(neuron, m)
    axes = np.concatenate([[axis_index], lattice_neighbours(layout.n_axes)[axis_index]])
    angles = np.array([angle_index - 1, angle_index, angle_index + 1]) % m
    return bool(code[neuron] >= code[(axes[:, None] * m + angles[None, :]).reshape(-1)].max())


def same_pose(layout: CodeLayout, R_a: np.ndarray, R_b: np.ndarray, symmetries: np.ndarray,
              radius_rad: float) -> bool:
    """True if rotation ``R_a`` is ``R_b`` up to the object's symmetries, within ``radius_rad``.

    ``symmetries`` ``(K, 3, 3)`` (identity included) act in the model frame, so
    the equivalents of ``R_b`` are ``R_b S_k``. Full codes: geodesic angle to
    the nearest equivalent below ``radius_rad``. Axis-only codes: only the
    symmetry-axis direction ``R a`` counts (the rotation about it is not
    observable), within ``radius_rad`` of the nearest ``R_b S_k a``.
    """
    if layout.axis_only:
        a = np.asarray(layout.symmetry_axis)
        directions = (R_b @ symmetries) @ a
        return bool(np.max(directions @ (R_a @ a)) >= np.cos(radius_rad))
    return bool(np.min(geodesic_angle(R_a, R_b @ symmetries)) < radius_rad)


def argmax_tolerance_rad(layout: CodeLayout) -> float:
    """How far apart [rad] two argmax decodes of one pose (up to symmetry) can lie: one grid step per coordinate.

    Argmax decodes are grid rotations. The equivalent ``R S_k`` of a decoded
    rotation is in general not one, and the peak of that pose sits on the grid
    rotation nearest to it, so two decodes of equivalent rotations differ by up
    to a step in each coordinate; half a step would call most genuine
    symmetric swaps different poses. On SO(3) an angle step moves a rotation by
    ``2 pi / m`` and an axis step ``delta`` (:attr:`CodeLayout.axis_spacing_rad`)
    moves a rotation of angle ``phi`` by ``2 sin(phi / 2) delta <= 2 delta``;
    the tolerance is the diagonal ``hypot(2 pi / m, 2 delta)``: 18.9 deg for
    642 x 36, 12.8 deg for the paper's 2562 x 36. Axis-only codes compare
    directions on the sphere: ``sqrt(2) delta`` (11.3 deg for 642 axes). The
    largest gaps measured stay just inside: ``bench/results/argmax-tolerance.md``.
    """
    if layout.axis_only:
        return float(np.sqrt(2.0) * layout.axis_spacing_rad)
    return float(np.hypot(2.0 * np.pi / layout.n_angles, 2.0 * layout.axis_spacing_rad))


def find_hypotheses(
    pc: PopulationCode,
    code: np.ndarray,
    symmetries: np.ndarray | None = None,
    top_k: int = 5,
    radius_deg: float | None = None,
    min_relative: float = DEFAULT_MIN_RELATIVE,
    refine: bool = True,
) -> list[Hypothesis]:
    """Distinct poses in one code row, strongest first (at most ``top_k``).

    ``radius_deg`` (default 2 sigma) is the suppression radius on SO(3);
    ``symmetries`` ``(K, 3, 3)`` merges peaks that are one pose. A code with
    no peak (flat, e.g. all zeros) is an error, not a guess.
    """
    layout = pc.layout
    code = check_code(code, layout.size)
    if len(code) != 1:
        raise PopcodeError(f"find_hypotheses takes one code row, got {len(code)}")
    code = code[0].astype(np.float64)
    top = float(code.max())
    if top <= 0 or np.ptp(code) < 1e-6 * max(abs(top), 1.0):
        raise PopcodeError("the code is flat: it has no peak, so it names no rotation")
    radius = np.deg2rad(2.0 * layout.sigma_deg if radius_deg is None else radius_deg)
    S = np.eye(3)[None] if symmetries is None else np.asarray(symmetries, dtype=np.float64)

    alive = code.copy()
    poses: list[list[np.ndarray]] = []
    activations: list[float] = []
    while len(poses) < top_k:
        neuron = int(np.argmax(alive))
        activation = float(alive[neuron])
        if not np.isfinite(activation) or activation < min_relative * top:
            break
        if not _is_local_maximum(layout, code, neuron):
            alive[neuron] = -np.inf  # the shoulder of a peak already taken
            continue
        alive[_suppression_mask(layout, neuron, radius)] = -np.inf
        R = refine_neuron(pc, code, neuron) if refine else pc.preferred_rotations(np.array([neuron]))[0]
        if any(same_pose(layout, R, member, np.eye(3)[None], radius) for members in poses for member in members):
            continue  # the axis/angle twin of a peak already found: the same rotation
        for members in poses:
            if same_pose(layout, R, members[0], S, radius):
                members.append(R)
                break
        else:
            poses.append([R])
            activations.append(activation)
    total = sum(activations)
    return [
        Hypothesis(R_m2c=members[0], activation=activation, score=activation / total, equivalent=np.stack(members))
        for members, activation in zip(poses, activations, strict=True)
    ]
