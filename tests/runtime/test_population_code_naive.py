"""A naive twin of ``PopulationCode.encode``: docs/design.md#population-code, neuron by neuron with plain loops.

Nothing here uses the runtime's lattice, axis/angle conversion or tuning code;
only the symmetry rotations (identity first) come from ``symmetry_rotations``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from symmetry_cases import CASES

from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.geometry.symmetries import symmetry_rotations

N_AXES, N_ANGLES, SIGMA_DEG = 42, 12, 25.0


def lattice_axis(i: int, n: int) -> tuple[float, float, float]:
    z = 1.0 - (2 * i + 1) / n
    rho = math.sqrt(1.0 - z * z)
    psi = i * math.pi * (3.0 - math.sqrt(5.0))
    return (rho * math.cos(psi), rho * math.sin(psi), z)


def axis_angle(R: list[list[float]]) -> tuple[tuple[float, float, float], float]:
    """Axis and angle in [0, pi] of a rotation matrix, from its trace and skew part (or R + I near pi)."""
    trace = R[0][0] + R[1][1] + R[2][2]
    angle = math.acos(max(-1.0, min(1.0, (trace - 1.0) / 2.0)))
    skew = (R[2][1] - R[1][2], R[0][2] - R[2][0], R[1][0] - R[0][1])
    if math.sin(angle) > 1e-3:
        axis = skew
    else:  # near pi: a column of R + I is along the axis; keep the sign the skew part gives
        columns = [[R[r][c] + (1.0 if r == c else 0.0) for r in range(3)] for c in range(3)]
        axis = max(columns, key=lambda col: sum(v * v for v in col))
        if sum(a * s for a, s in zip(axis, skew, strict=True)) < 0:
            axis = [-v for v in axis]
    norm = math.sqrt(sum(v * v for v in axis))
    return (axis[0] / norm, axis[1] / norm, axis[2] / norm), angle


def angular_distance(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return math.acos(max(-1.0, min(1.0, sum(x * y for x, y in zip(a, b, strict=True)))))


def wrapped(a: float, b: float) -> float:
    d = (a - b) % (2.0 * math.pi)
    return min(d, 2.0 * math.pi - d)


def matmul(A: list[list[float]], B: list[list[float]]) -> list[list[float]]:
    return [[sum(A[r][k] * B[k][c] for k in range(3)) for c in range(3)] for r in range(3)]


def naive_full_code(R: np.ndarray, symmetries: np.ndarray) -> list[float]:
    sigma = math.radians(SIGMA_DEG)
    peaks = []
    for S in symmetries:
        axis, angle = axis_angle(matmul(R.tolist(), S.tolist()))
        peaks += [(axis, angle), (tuple(-v for v in axis), 2.0 * math.pi - angle)]  # and its twin
    code = []
    for i in range(N_AXES):
        u = lattice_axis(i, N_AXES)
        for j in range(N_ANGLES):
            phi_j = 2.0 * math.pi * j / N_ANGLES
            code.append(sum(math.exp(-(angular_distance(r, u) ** 2 + wrapped(phi, phi_j) ** 2) / (2 * sigma ** 2))
                            for r, phi in peaks))
    return code


def naive_axis_only_code(R: np.ndarray, symmetries: np.ndarray, a: tuple[float, float, float]) -> list[float]:
    sigma = math.radians(SIGMA_DEG)
    directions: list[tuple[float, ...]] = []
    for S in symmetries:
        RS = matmul(R.tolist(), S.tolist())
        d = tuple(sum(RS[r][c] * a[c] for c in range(3)) for r in range(3))
        if all(angular_distance(d, seen) > 1e-6 for seen in directions):
            directions.append(d)
    return [sum(math.exp(-angular_distance(d, lattice_axis(i, N_AXES)) ** 2 / (2 * sigma ** 2)) for d in directions)
            for i in range(N_AXES)]


def quaternion_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rotations(count: int, seed: int) -> list[np.ndarray]:
    """Uniform random rotations from normalised Gaussian quaternions."""
    q = np.random.default_rng(seed).normal(size=(count, 4))
    return [quaternion_matrix(*row) for row in q / np.linalg.norm(q, axis=1, keepdims=True)]


@pytest.mark.parametrize("case", ["none", "two_fold", "four_fold"])
def test_full_code_is_the_design_formula(case: str) -> None:
    code = PopulationCode(CodeLayout(N_AXES, N_ANGLES, SIGMA_DEG))
    symmetries = symmetry_rotations(CASES[case])
    for R in rotations(3, seed=len(case)):
        np.testing.assert_allclose(code.encode(R, symmetries), naive_full_code(R, symmetries), atol=2e-6)


@pytest.mark.parametrize("case", ["continuous", "continuous_flip"])
def test_axis_only_code_is_the_design_formula(case: str) -> None:
    a = (0.0, 0.0, 1.0)  # the cases' symmetry axis
    code = PopulationCode(CodeLayout(N_AXES, N_ANGLES, SIGMA_DEG, axis_only=True, symmetry_axis=a))
    symmetries = symmetry_rotations(CASES[case])
    for R in rotations(3, seed=len(case)):
        np.testing.assert_allclose(code.encode(R, symmetries), naive_axis_only_code(R, symmetries, a), atol=2e-6)
