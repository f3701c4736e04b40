"""Sub-neuron decoding: locate the rotation between grid points from the activations around a peak.

The tuning is Gaussian, so near a peak the log-activation is a quadratic
function of the distance to the encoded value. Fitting that quadratic to the
peak neuron and its lattice neighbours (a 2-D fit in the tangent plane of the
axis sphere, a 1-D fit along the angle circle) puts the estimate between grid
points. The fit has a free height and curvature, so it does not care whether
the network's peaks are as tall or as wide as the training targets.

Only the peak's own neighbourhood is used: other symmetric peaks, and the
axis/angle twin (which sits at the antipodal axis), are never mixed in.

The three-neuron fit was chosen by measurement against wider fits, templates
and circular means: ``bench/results/refined-decoder.md``.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ..geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rotation_between
from .population_code import CodeLayout, DecodedRotations, PopulationCode, check_code, fibonacci_lattice

NEIGHBOURS = 8  # lattice neighbours of a peak used for the axis fit (Fibonacci cells have ~6)
_LOG_FLOOR = 1e-6


@lru_cache(maxsize=8)
def lattice_neighbours(n_axes: int, count: int = NEIGHBOURS) -> np.ndarray:
    """Indices ``(n, count)`` of each lattice axis's nearest other axes, nearest first."""
    axes = fibonacci_lattice(n_axes)
    count = min(count, n_axes - 1)
    result = np.empty((n_axes, count), dtype=np.int64)
    for start in range(0, n_axes, 1024):
        dots = axes[start : start + 1024] @ axes.T
        dots[np.arange(len(dots)), np.arange(start, start + len(dots))] = -np.inf  # not itself
        nearest = np.argpartition(-dots, count, axis=1)[:, :count]
        order = np.argsort(-np.take_along_axis(dots, nearest, axis=1), axis=1)
        result[start : start + 1024] = np.take_along_axis(nearest, order, axis=1)
    return result


def _tangent_basis(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def refine_axis(layout: CodeLayout, peak_axis: int, activations: np.ndarray) -> np.ndarray:
    """Unit direction ``(3,)`` near lattice axis ``peak_axis`` from activations of all ``n`` axes.

    Weighted least squares of ``log a = c + g.x - k |x|^2`` over the peak and
    its neighbours, ``x`` being azimuthal-equidistant coordinates about the
    peak axis; the vertex ``g / 2k`` is the estimate, kept within one lattice
    spacing of the peak.
    """
    axes = layout.axes
    u = axes[peak_axis]
    members = np.concatenate([[peak_axis], lattice_neighbours(layout.n_axes)[peak_axis]])
    values = np.maximum(activations[members], _LOG_FLOOR)
    e1, e2 = _tangent_basis(u)
    others = axes[members]
    theta = np.arccos(np.clip(others @ u, -1.0, 1.0))
    tangent = others - np.outer(others @ u, u)
    norms = np.linalg.norm(tangent, axis=1)
    direction = np.divide(tangent, norms[:, None], out=np.zeros_like(tangent), where=norms[:, None] > 1e-12)
    x = theta[:, None] * np.stack([direction @ e1, direction @ e2], axis=1)
    design = np.column_stack([np.ones(len(x)), x, -(x**2).sum(axis=1)])
    weights = values / values.max()
    coef, *_ = np.linalg.lstsq(design * weights[:, None], np.log(values) * weights, rcond=None)
    _, g1, g2, curvature = coef
    if curvature <= 0:
        return u
    offset = np.array([g1, g2]) / (2.0 * curvature)
    spacing = layout.axis_spacing_rad
    length = np.linalg.norm(offset)
    if length > spacing:
        offset *= spacing / length
        length = spacing
    if length < 1e-12:
        return u
    step = (offset[0] * e1 + offset[1] * e2) / length
    return np.cos(length) * u + np.sin(length) * step


def refine_angle(layout: CodeLayout, peak_angle: int, activations: np.ndarray) -> float:
    """Angle (rad) near preferred angle ``peak_angle`` from the ``m`` activations of one axis.

    A parabola through the log-activations of the peak and its two neighbours
    on the circle (exact for a Gaussian); its vertex is kept within half a step.
    """
    m = layout.n_angles
    step = 2.0 * np.pi / m
    left, centre, right = np.log(np.maximum(activations[[(peak_angle - 1) % m, peak_angle, (peak_angle + 1) % m]],
                                            _LOG_FLOOR))
    denominator = left - 2.0 * centre + right
    offset = 0.0 if denominator >= 0 else float(np.clip(0.5 * (left - right) / denominator, -0.5, 0.5))
    return float(layout.angles_rad[peak_angle] + offset * step)


def fit_neurons(layout: CodeLayout, neuron: int) -> np.ndarray:
    """The neurons whose activations :func:`refine_neuron` reads, the peak first."""
    if layout.axis_only:
        return np.concatenate([[neuron], lattice_neighbours(layout.n_axes)[neuron]])
    m = layout.n_angles
    axis_index, angle_index = divmod(int(neuron), m)
    along_angle = axis_index * m + np.array([(angle_index - 1) % m, (angle_index + 1) % m])
    along_axes = lattice_neighbours(layout.n_axes)[axis_index] * m + angle_index
    return np.concatenate([[neuron], along_angle, along_axes])


def refine_neuron(pc: PopulationCode, code: np.ndarray, neuron: int) -> np.ndarray:
    """Refined rotation ``(3, 3)`` for the peak at ``neuron`` of one code row."""
    layout = pc.layout
    if layout.axis_only:
        direction = refine_axis(layout, neuron, code)
        return rotation_between(np.asarray(layout.symmetry_axis), direction)
    grid = code.reshape(layout.n_axes, layout.n_angles)
    axis_index, angle_index = divmod(int(neuron), layout.n_angles)
    angle = refine_angle(layout, angle_index, grid[axis_index])
    axis = refine_axis(layout, axis_index, grid[:, angle_index])
    return axis_angle_to_matrix(axis, angle)


def refine_with_symmetries(pc: PopulationCode, code: np.ndarray, neuron: int, symmetries: np.ndarray,
                           passes: int = 2) -> np.ndarray:
    """Refined rotation for the peak at ``neuron``, with the other symmetric peaks explained away.

    The tails of an object's equivalent poses (90 deg apart for a 4-fold part)
    tilt the log-activations around a peak and bias the local fit. Knowing the
    symmetries, the code those other poses would produce is subtracted (scaled
    to the peak's height) and the fit repeated.
    """
    R = refine_neuron(pc, code, neuron)
    if len(symmetries) < 2:
        return R
    patch = fit_neurons(pc.layout, neuron)  # only these enter the fit: model the others there alone
    cleaned = code.astype(np.float64)
    for _ in range(passes):
        own = pc.encode(R, neurons=patch)
        others = pc.encode(R, symmetries, neurons=patch) - own
        height = code[neuron] / max(float(own[0]), 1e-6)
        cleaned[patch] = code[patch] - height * others
        R = refine_neuron(pc, cleaned, neuron)
    return R


def decode_refined(pc: PopulationCode, code: np.ndarray, symmetries: np.ndarray | None = None) -> DecodedRotations:
    """Like :meth:`PopulationCode.decode`, with each argmax refined between grid points.

    ``symmetries`` ``(K, 3, 3)`` (identity first), when known, let the fit discount the other peaks.
    """
    code = check_code(code, pc.layout.size)
    neuron = np.argmax(code, axis=1)
    S = np.eye(3)[None] if symmetries is None else np.asarray(symmetries, dtype=np.float64)
    R = np.stack([refine_with_symmetries(pc, row, k, S) for row, k in zip(code, neuron, strict=True)])
    axis, angle = matrix_to_axis_angle(R)
    activation = code[np.arange(len(code)), neuron]
    return DecodedRotations(R=R, axis=axis, angle_rad=angle, neuron=neuron, activation=activation)
