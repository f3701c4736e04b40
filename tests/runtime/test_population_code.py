import numpy as np
import pytest
from symmetry_cases import AXIS_DIRECTIONS, CASES, DISCRETE_ORDER

from popcode_runtime import CodeLayout, PopcodeError, PopulationCode, fibonacci_lattice, symmetry_rotations
from popcode_runtime.geometry.rotations import geodesic_angle, matrix_to_axis_angle, random_rotations
from popcode_runtime.geometry.symmetries import continuous_axis

SMALL = {"n_axes": 642, "n_angles": 36, "sigma_deg": 20.0}


def lattice_covering_radius(axes: np.ndarray, rng: np.random.Generator, samples: int = 50000) -> float:
    """Largest angle from a random direction to its nearest lattice axis (estimated by sampling)."""
    d = rng.normal(size=(samples, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return float(np.arccos(np.clip((d @ axes.T).max(axis=1), -1, 1)).max())


def test_fibonacci_lattice_formula_and_uniformity():
    n = 2562
    axes = fibonacci_lattice(n)
    np.testing.assert_allclose(np.linalg.norm(axes, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(axes[:, 2], 1 - (2 * np.arange(n) + 1) / n)
    psi = np.arange(n) * np.pi * (3 - np.sqrt(5))
    np.testing.assert_allclose(np.arctan2(axes[:, 1], axes[:, 0]), np.angle(np.exp(1j * psi)), atol=1e-9)
    # Near-uniform: nearest-neighbour angles cluster around the spacing sqrt(4 pi / n).
    cos = axes @ axes.T
    np.fill_diagonal(cos, -1)
    nearest = np.arccos(np.clip(cos.max(axis=1), -1, 1))
    spacing = np.sqrt(4 * np.pi / n)
    assert 0.7 * spacing < nearest.min() and nearest.max() < 1.3 * spacing
    assert abs(axes.mean(axis=0)).max() < 1e-3  # no preferred direction


def test_layout_size_and_index():
    layout = CodeLayout()
    assert layout.size == 2562 * 36
    code = PopulationCode(layout)
    # Neuron k = i * m + j prefers axis i and angle j.
    k = 5 * 36 + 7
    axis, angle = matrix_to_axis_angle(code.preferred_rotations(np.array([k])))
    twin_ok = np.allclose(axis[0], layout.axes[5]) and np.isclose(angle[0], layout.angles_rad[7])
    flipped_ok = np.allclose(axis[0], -layout.axes[5]) and np.isclose(angle[0], 2 * np.pi - layout.angles_rad[7])
    assert twin_ok or flipped_ok
    axis_only = CodeLayout(axis_only=True, symmetry_axis=(0, 0, 2))
    assert axis_only.size == 2562 and axis_only.symmetry_axis == (0.0, 0.0, 1.0)


def test_layout_round_trips_and_rejects_bad_values():
    layout = CodeLayout(n_axes=42, n_angles=12, sigma_deg=15.0, axis_only=True, symmetry_axis=(1, 0, 0))
    assert CodeLayout.from_dict(layout.to_dict()) == layout
    with pytest.raises(PopcodeError, match="symmetry_axis"):
        CodeLayout(axis_only=True)
    with pytest.raises(PopcodeError, match="sigma"):
        CodeLayout(sigma_deg=0)
    with pytest.raises(PopcodeError, match="unknown code layout keys"):
        CodeLayout.from_dict({"n_axes": 4, "bogus": 1})


def count_peaks(code: np.ndarray, pc: PopulationCode, radius_rad: float, floor: float = 0.5) -> int:
    """Peaks by non-maximum suppression in the axis x angle product space."""
    layout = pc.layout
    m = layout.n_angles
    alive = code.copy()
    peaks = 0
    while alive.max() > floor * code.max():
        k = int(np.argmax(alive))
        i, j = divmod(k, m)
        dtheta = np.arccos(np.clip(layout.axes @ layout.axes[i], -1, 1))
        dphi = np.abs(np.angle(np.exp(1j * (layout.angles_rad - layout.angles_rad[j]))))
        near = (dtheta[:, None] ** 2 + dphi[None, :] ** 2) < radius_rad**2
        alive[near.reshape(-1)] = -np.inf
        peaks += 1
    return peaks


def rotations_with_clear_peaks(S: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """Rotations whose equivalent poses all have angles in [40, 140] deg (peaks far from the 0/pi seams)."""
    kept = []
    while len(kept) < count:
        R = random_rotations(1, rng)[0]
        _, angles = matrix_to_axis_angle(R @ S)
        if np.all((angles > np.deg2rad(40)) & (angles < np.deg2rad(140))):
            kept.append(R)
    return np.stack(kept)


@pytest.mark.parametrize("name", ["none", "two_fold", "four_fold"])
def test_target_has_two_peaks_per_equivalent_pose(name):
    rng = np.random.default_rng(7)
    pc = PopulationCode(CodeLayout(**SMALL))
    S = symmetry_rotations(CASES[name])
    for R in rotations_with_clear_peaks(S, 5, rng):
        code = pc.encode(R, S)
        assert code.dtype == np.float32 and code.shape == (pc.layout.size,)
        assert count_peaks(code, pc, radius_rad=np.deg2rad(40)) == 2 * DISCRETE_ORDER[name]


@pytest.mark.parametrize("name", ["continuous", "continuous_flip"])
def test_axis_only_target_has_one_peak_per_axis_direction(name):
    rng = np.random.default_rng(8)
    info = CASES[name]
    layout = CodeLayout(n_axes=642, axis_only=True, symmetry_axis=tuple(continuous_axis(info)))
    pc = PopulationCode(layout)
    for R in random_rotations(5, rng):
        code = pc.encode(R, symmetry_rotations(info))
        assert code.shape == (642,)
        # Peaks on the sphere: NMS with a 40 deg radius.
        alive, peaks = code.copy(), 0
        while alive.max() > 0.5 * code.max():
            k = int(np.argmax(alive))
            alive[np.arccos(np.clip(layout.axes @ layout.axes[k], -1, 1)) < np.deg2rad(40)] = -np.inf
            peaks += 1
        assert peaks == AXIS_DIRECTIONS[name]


def test_peak_value_is_the_gaussian_of_the_grid_distance():
    pc = PopulationCode(CodeLayout(**SMALL))
    R = pc.preferred_rotations(np.array([100 * 36 + 9]))[0]  # exactly on a neuron
    code = pc.encode(R)
    assert int(np.argmax(code)) == 100 * 36 + 9
    assert code[100 * 36 + 9] == pytest.approx(1.0, abs=1e-3)  # its own Gaussian, plus far tails


@pytest.mark.parametrize("name", ["none", "two_fold", "four_fold"])
def test_full_code_round_trip_within_grid_resolution(name):
    """Argmax lands on the neuron nearest (in dtheta^2 + dphi^2) to one of the encoded peaks.

    Then dtheta^2 + dphi^2 <= rho^2 with rho^2 = c^2 + (pi/m)^2 (c: lattice covering
    radius), and the rotation error is at most dphi + 2 dtheta <= sqrt(5) rho.
    """
    rng = np.random.default_rng(11)
    layout = CodeLayout()
    pc = PopulationCode(layout)
    S = symmetry_rotations(CASES[name])
    R = random_rotations(300, rng)
    decoded = pc.decode(pc.encode(R, S))
    errors = np.min(geodesic_angle(decoded.R[:, None], R[:, None] @ S[None]), axis=1)
    c = lattice_covering_radius(layout.axes, rng)
    rho = np.hypot(c, np.pi / layout.n_angles)
    assert errors.max() <= np.sqrt(5) * rho
    # The grid is fine enough that typical errors are a fraction of that bound.
    assert np.median(errors) < rho


@pytest.mark.parametrize("name", ["continuous", "continuous_flip"])
def test_axis_only_round_trip_hits_nearest_lattice_axis(name):
    rng = np.random.default_rng(12)
    info = CASES[name]
    a = continuous_axis(info)
    layout = CodeLayout(axis_only=True, symmetry_axis=tuple(a))
    pc = PopulationCode(layout)
    S = symmetry_rotations(info)
    R = random_rotations(300, rng)
    decoded = pc.decode(pc.encode(R, S))
    predicted = decoded.R @ a
    truth = np.einsum("nij,kj->nki", R, S @ a)  # every equivalent direction
    angle = np.arccos(np.clip(np.einsum("ni,nki->nk", predicted, truth), -1, 1)).min(axis=1)
    # The winner is the lattice axis nearest to the true direction (up to the symmetry).
    nearest = np.arccos(np.clip(np.einsum("nki,ai->nka", truth, layout.axes).max(axis=2), -1, 1)).min(axis=1)
    np.testing.assert_allclose(angle, nearest, atol=1e-9)
    assert decoded.activation.min() > 0.9


def test_decode_rejects_bad_codes():
    pc = PopulationCode(CodeLayout(**SMALL))
    with pytest.raises(PopcodeError, match="shape"):
        pc.decode(np.zeros((2, 10), np.float32))
    bad = np.zeros((2, pc.layout.size), np.float32)
    bad[1, 3] = np.nan
    with pytest.raises(PopcodeError, match="NaN"):
        pc.decode(bad)


def test_encoding_is_batched_and_matches_single():
    rng = np.random.default_rng(3)
    pc = PopulationCode(CodeLayout(**SMALL))
    S = symmetry_rotations(CASES["two_fold"])
    R = random_rotations(4, rng)
    batch = pc.encode(R, S)
    np.testing.assert_allclose(batch[2], pc.encode(R[2], S), rtol=1e-6)
