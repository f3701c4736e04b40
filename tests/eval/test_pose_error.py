"""Pose errors on hand-checkable cases: a cube, a symmetric pose, synthetic depth images."""

from __future__ import annotations

import numpy as np
import pytest
from symmetry_cases import CASES

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, random_rotations
from popcode_runtime.geometry.symmetries import symmetry_transforms
from popcode_trainer.metrics import pose_errors as pose_error
from popcode_trainer.metrics.pose_errors import (
    add,
    adi,
    mspd,
    mssd,
    rotation_error_deg,
    translation_error_mm,
    vsd,
    vsd_from_depths,
)

HALF_MM = 50.0
CUBE_MM = HALF_MM * np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
K = np.array([[1000.0, 0.0, 320.0], [0.0, 1000.0, 240.0], [0.0, 0.0, 1.0]])
T_MM = np.array([0.0, 0.0, 1000.0])
RZ90 = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.pi / 2)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(5)


def test_identity_pose_has_zero_error_for_every_vertex_metric():
    syms = symmetry_transforms(CASES["four_fold"])
    I = np.eye(3)
    assert float(mssd(I, T_MM, I, T_MM, CUBE_MM, syms)) == 0.0
    assert float(mspd(I, T_MM, I, T_MM, K, CUBE_MM, syms)) == 0.0
    assert float(add(I, T_MM, I, T_MM, CUBE_MM)) == 0.0
    assert float(adi(I, T_MM, I, T_MM, CUBE_MM)) == 0.0
    assert float(rotation_error_deg(I, I)) == 0.0
    assert float(translation_error_mm(T_MM, T_MM)) == 0.0


def test_cube_quarter_turn_without_symmetry_moves_every_vertex_by_the_edge_length():
    # Each vertex lies sqrt(2) a from the z axis; a 90 degree turn moves it 2 sqrt(2) a sin(45) = 2a.
    assert float(mssd(RZ90, T_MM, np.eye(3), T_MM, CUBE_MM, None)) == pytest.approx(2 * HALF_MM)
    assert float(add(RZ90, T_MM, np.eye(3), T_MM, CUBE_MM)) == pytest.approx(2 * HALF_MM)
    assert float(rotation_error_deg(RZ90, np.eye(3))) == pytest.approx(90.0)


def test_cube_quarter_turn_with_four_fold_symmetry_is_no_error():
    syms = symmetry_transforms(CASES["four_fold"])
    assert float(mssd(RZ90, T_MM, np.eye(3), T_MM, CUBE_MM, syms)) == pytest.approx(0.0, abs=1e-9)
    assert float(mspd(RZ90, T_MM, np.eye(3), T_MM, K, CUBE_MM, syms)) == pytest.approx(0.0, abs=1e-9)
    # The vertex set maps onto itself, so ADI is zero too; ADD is blind to symmetry.
    assert float(adi(RZ90, T_MM, np.eye(3), T_MM, CUBE_MM)) == pytest.approx(0.0, abs=1e-9)
    assert float(add(RZ90, T_MM, np.eye(3), T_MM, CUBE_MM)) == pytest.approx(2 * HALF_MM)


def test_cube_quarter_turn_mspd_matches_a_hand_projection():
    # Vertex (x, y, z) goes to (-y, x, z): with |x| = |y| = a one image coordinate moves by
    # f 2a / (t_z + z) and the other not at all; the near face (z = -a) moves most.
    expected_px = 1000.0 * 2 * HALF_MM / (1000.0 - HALF_MM)
    assert float(mspd(RZ90, T_MM, np.eye(3), T_MM, K, CUBE_MM, None)) == pytest.approx(expected_px)


def test_ground_truth_composed_with_a_symmetry_has_zero_symmetric_error(rng):
    syms = symmetry_transforms(CASES["continuous_flip"])
    pts = rng.normal(size=(200, 3)) * [30.0, 20.0, 10.0]
    R_gt = random_rotations(1, rng)[0]
    for k in (len(syms) // 8, len(syms) // 2, len(syms) - 50):  # quarter turn, flip, flip + turn
        R_est = R_gt @ syms.R[k]
        t_est = R_gt @ syms.t_mm[k] + T_MM
        assert float(mssd(R_est, t_est, R_gt, T_MM, pts, syms)) == pytest.approx(0.0, abs=1e-9)
        assert float(mspd(R_est, t_est, R_gt, T_MM, K, pts, syms)) == pytest.approx(0.0, abs=1e-9)
        assert float(add(R_est, t_est, R_gt, T_MM, pts)) > 1.0


def test_adi_never_exceeds_add_or_mssd(rng):
    pts = rng.normal(size=(300, 3)) * [40.0, 25.0, 15.0]
    R_est, R_gt = random_rotations(20, rng), random_rotations(20, rng)
    e_adi, e_add = adi(R_est, T_MM, R_gt, T_MM, pts), add(R_est, T_MM, R_gt, T_MM, pts)
    assert e_adi.shape == (20,)
    assert np.all(e_adi <= e_add + 1e-9)
    assert np.all(e_add <= mssd(R_est, T_MM, R_gt, T_MM, pts, None) + 1e-9)


def test_batch_equals_single_poses_and_chunking_changes_nothing(rng, monkeypatch):
    syms = symmetry_transforms(CASES["continuous"])
    pts = rng.normal(size=(50, 3)) * 20.0
    R_est, R_gt = random_rotations(5, rng), random_rotations(5, rng)
    t_est = T_MM + rng.normal(size=(5, 3))
    batch = mssd(R_est, t_est, R_gt, T_MM, pts, syms)
    single = [float(mssd(R_est[i], t_est[i], R_gt[i], T_MM, pts, syms)) for i in range(5)]
    np.testing.assert_allclose(batch, single)
    batch_px = mspd(R_est, t_est, R_gt, T_MM, K, pts, syms)
    monkeypatch.setattr(pose_error, "_CHUNK_ELEMENTS", 120)
    np.testing.assert_allclose(mssd(R_est, t_est, R_gt, T_MM, pts, syms), batch)
    np.testing.assert_allclose(mspd(R_est, t_est, R_gt, T_MM, K, pts, syms), batch_px)
    np.testing.assert_allclose(adi(R_est, t_est, R_gt, T_MM, pts), [
        float(adi(R_est[i], t_est[i], R_gt[i], T_MM, pts)) for i in range(5)])


def test_translation_error_is_euclidean():
    assert float(translation_error_mm(np.array([3.0, 4.0, 0.0]), np.zeros(3))) == pytest.approx(5.0)


def test_bad_shapes_are_reported():
    with pytest.raises(PopcodeError, match="rotations"):
        mssd(np.eye(4), T_MM, np.eye(3), T_MM, CUBE_MM, None)
    with pytest.raises(PopcodeError, match="model points"):
        add(np.eye(3), T_MM, np.eye(3), T_MM, CUBE_MM[:, :2])


# --- VSD on synthetic depth images: fronto-parallel rectangles, a numpy z-buffer by hand.

H, W = 60, 80
K_SMALL = np.array([[2000.0, 0.0, 40.0], [0.0, 2000.0, 30.0], [0.0, 0.0, 1.0]])
DELTA_MM = 15.0


def box(x0: int, x1: int, y0: int, y1: int, z_mm: float, base: np.ndarray | None = None) -> np.ndarray:
    """Depth image with a rectangle at depth ``z_mm`` drawn in front of ``base`` (z-buffer)."""
    depth = np.zeros((H, W), np.float32) if base is None else base.copy()
    patch = depth[y0:y1, x0:x1]
    depth[y0:y1, x0:x1] = np.where((patch == 0) | (patch > z_mm), z_mm, patch)
    return depth


def test_vsd_identical_renderings_is_zero_for_every_tau():
    gt = box(20, 60, 10, 50, 1000.0)
    errors = vsd_from_depths(gt, gt, gt, K_SMALL, DELTA_MM, [5.0, 20.0, np.inf])
    np.testing.assert_array_equal(errors, 0.0)


def test_vsd_disjoint_silhouettes_is_one():
    gt, est = box(45, 75, 10, 50, 1000.0), box(5, 35, 10, 50, 1000.0)
    np.testing.assert_array_equal(vsd_from_depths(est, gt, gt, K_SMALL, DELTA_MM, [20.0, np.inf]), 1.0)


def test_vsd_half_overlap_is_two_thirds():
    gt, est = box(20, 40, 10, 50, 1000.0), box(30, 50, 10, 50, 1000.0)
    # Union 3 halves, intersection 1 half, equal depth in the intersection.
    np.testing.assert_allclose(vsd_from_depths(est, gt, gt, K_SMALL, DELTA_MM, [20.0]), [2 / 3])


def test_vsd_depth_offset_counts_beyond_tau_only():
    gt, est = box(20, 60, 10, 50, 1000.0), box(20, 60, 10, 50, 1030.0)
    # Near the optical axis the 30 mm depth offset is a ~30 mm distance offset; the estimate
    # lies behind the scene but counts as visible where the ground truth is visible.
    errors = vsd_from_depths(est, gt, gt, K_SMALL, DELTA_MM, [20.0, 40.0, np.inf])
    np.testing.assert_array_equal(errors, [1.0, 0.0, 0.0])


def test_vsd_taus_as_fraction_of_the_diameter():
    gt, est = box(20, 60, 10, 50, 1000.0), box(20, 60, 10, 50, 1030.0)
    errors = vsd_from_depths(est, gt, gt, K_SMALL, DELTA_MM, [0.2, 0.4], diameter_mm=100.0)
    np.testing.assert_array_equal(errors, [1.0, 0.0])


def test_vsd_ignores_the_occluded_part_of_the_object():
    gt = box(20, 60, 10, 50, 1000.0)
    scene = box(20, 40, 10, 50, 900.0, base=gt)  # an occluder hides the left half
    est = box(40, 60, 10, 50, 1000.0)  # differs only where the object is hidden
    np.testing.assert_array_equal(vsd_from_depths(est, gt, scene, K_SMALL, DELTA_MM, [20.0]), [0.0])


def test_vsd_with_nothing_visible_is_one():
    empty = np.zeros((H, W), np.float32)
    np.testing.assert_array_equal(vsd_from_depths(empty, empty, empty, K_SMALL, DELTA_MM, [20.0]), [1.0])


def test_vsd_renders_both_poses_with_the_injected_renderer():
    calls = []

    def render_depth(R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
        calls.append(t_mm.copy())
        x0 = 20 + int(t_mm[0])  # a translation of 1 mm shifts the box by one pixel
        return box(x0, x0 + 20, 10, 50, float(t_mm[2]))

    scene = box(20, 40, 10, 50, 1000.0)
    errors = vsd(np.eye(3), np.array([10.0, 0, 1000]), np.eye(3), np.array([0.0, 0, 1000]), scene, K_SMALL,
                 render_depth, DELTA_MM, [20.0, np.inf])
    np.testing.assert_allclose(errors, [2 / 3, 2 / 3])
    assert [c[0] for c in calls] == [10.0, 0.0]


def test_vsd_rejects_images_of_different_sizes():
    with pytest.raises(PopcodeError, match="differ in size"):
        vsd_from_depths(np.zeros((H, W)), np.zeros((H, W)), np.zeros((H + 1, W)), K_SMALL, DELTA_MM, [20.0])
