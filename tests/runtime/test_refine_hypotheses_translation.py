"""Beyond the paper's decoder: sub-neuron estimates, every symmetric mode, translation from the box."""

import numpy as np
import pytest
from onnx_models import linear_model, save
from symmetry_cases import CASES

from popcode_runtime import (
    CodeLayout,
    ModelMetadata,
    PopcodeError,
    PopulationCode,
    PoseEstimator,
    Representation,
    symmetry_rotations,
)
from popcode_runtime.coding.hypotheses import argmax_tolerance_rad, find_hypotheses, same_pose
from popcode_runtime.coding.refine import decode_refined, lattice_neighbours
from popcode_runtime.geometry.camera import project_camera_points
from popcode_runtime.geometry.crop import box_edges, box_from_edges
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, geodesic_angle, random_rotations
from popcode_runtime.geometry.symmetries import continuous_axis
from popcode_runtime.geometry.translation import object_points_mm, translation_from_box
from popcode_runtime.model.decoding import decode_output

PAPER = CodeLayout()
K = np.array([[1075.65, 0.0, 360.0], [0.0, 1073.9, 270.0], [0.0, 0.0, 1.0]])


def symmetric_error_deg(R_est, R_gt, S):
    return np.degrees(np.min(geodesic_angle(R_est[:, None], R_gt[:, None] @ S[None]), axis=1))


@pytest.mark.parametrize("name", ["none", "two_fold"])
def test_refined_recovers_off_grid_rotations_far_below_the_grid(name):
    """An exact code of a random (off-grid) rotation is a sum of Gaussians; the local
    log-quadratic fit is exact up to the curvature of the sphere over one lattice cell,
    so the refined estimate is within 0.05 deg (argmax is only within ~6 deg: the grid)."""
    rng = np.random.default_rng(21)
    pc = PopulationCode(PAPER)
    S = symmetry_rotations(CASES[name])
    R = random_rotations(200, rng)
    code = pc.encode(R, S)
    refined = symmetric_error_deg(decode_refined(pc, code).R, R, S)
    argmax = symmetric_error_deg(pc.decode(code).R, R, S)
    assert refined.max() < 0.05
    assert np.median(argmax) > 20 * np.median(refined)


def test_refined_axis_only_code():
    rng = np.random.default_rng(22)
    info = CASES["continuous_flip"]
    a = continuous_axis(info)
    pc = PopulationCode(CodeLayout(axis_only=True, symmetry_axis=tuple(a)))
    S = symmetry_rotations(info)
    R = random_rotations(200, rng)
    decoded = decode_refined(pc, pc.encode(R, S)).R @ a
    truth = np.einsum("nij,kj->nki", R, S @ a)
    error = np.degrees(np.arccos(np.clip(np.einsum("ni,nki->nk", decoded, truth).max(axis=1), -1, 1)))
    assert error.max() < 0.05


def test_refined_estimate_lies_on_one_pose_never_between_two():
    """For a 4-fold object the four equivalent poses are 90 deg apart; the estimate sits at one."""
    rng = np.random.default_rng(23)
    pc = PopulationCode(PAPER)
    S = symmetry_rotations(CASES["four_fold"])
    R = random_rotations(100, rng)
    errors = geodesic_angle(decode_refined(pc, pc.encode(R, S)).R[:, None], R[:, None] @ S[None])
    nearest = np.sort(np.degrees(errors), axis=1)
    # The neighbouring peaks' tails bias the fit a little, but the estimate is at one pose, far from the others.
    assert nearest[:, 0].max() < 6.0 and nearest[:, 1].min() > 80.0


def test_refined_handles_angle_wrap_and_twin_seam():
    pc = PopulationCode(PAPER)
    for angle_deg in (0.5, 4.0, 179.5, 175.0):
        R = axis_angle_to_matrix(np.array([0.3, -0.5, 0.81]), np.deg2rad(angle_deg))[None]
        assert symmetric_error_deg(decode_refined(pc, pc.encode(R)).R, R, np.eye(3)[None])[0] < 0.1


def test_lattice_neighbours_are_the_nearest_axes():
    neighbours = lattice_neighbours(642)
    axes = PopulationCode(CodeLayout(n_axes=642)).layout.axes
    dots = axes @ axes.T
    np.fill_diagonal(dots, -2)
    np.testing.assert_array_equal(np.sort(neighbours, axis=1), np.sort(np.argsort(-dots, axis=1)[:, :8], axis=1))


def test_hypotheses_of_an_exact_two_fold_code():
    rng = np.random.default_rng(24)
    pc = PopulationCode(PAPER)
    S = symmetry_rotations(CASES["two_fold"])
    for R in random_rotations(10, rng):
        code = pc.encode(R, S)
        found = find_hypotheses(pc, code)  # no symmetry information: both poses
        assert len(found) == 2
        assert {int(np.argmin(geodesic_angle(h.R_m2c, R @ S))) for h in found} == {0, 1}
        assert sum(h.score for h in found) == pytest.approx(1.0)
        for h in found:
            assert np.degrees(geodesic_angle(h.R_m2c, R @ S).min()) < 0.05
        merged = find_hypotheses(pc, code, symmetries=S)  # with it: one pose, two equivalent peaks
        assert len(merged) == 1 and len(merged[0].equivalent) == 2 and merged[0].score == pytest.approx(1.0)


def test_hypotheses_of_four_fold_and_asymmetric_codes():
    rng = np.random.default_rng(25)
    pc = PopulationCode(PAPER)
    for name, count in (("none", 1), ("four_fold", 4)):
        S = symmetry_rotations(CASES[name])
        for R in random_rotations(5, rng):
            found = find_hypotheses(pc, pc.encode(R, S), top_k=10)
            assert len(found) == count
            merged = find_hypotheses(pc, pc.encode(R, S), symmetries=S, top_k=10)
            assert len(merged) == 1 and len(merged[0].equivalent) == count


def test_hypotheses_of_two_different_poses_are_ranked_by_activation():
    rng = np.random.default_rng(26)
    pc = PopulationCode(PAPER)
    R_strong, R_weak = random_rotations(2, rng)
    code = pc.encode(R_strong) + 0.5 * pc.encode(R_weak)
    found = find_hypotheses(pc, code)
    assert len(found) == 2
    assert np.degrees(geodesic_angle(found[0].R_m2c, R_strong)) < 0.5
    assert np.degrees(geodesic_angle(found[1].R_m2c, R_weak)) < 0.5
    assert found[0].score == pytest.approx(2 / 3, abs=0.02)


@pytest.mark.parametrize("n_axes,n_angles", [(162, 36), (642, 36), (642, 18)])
def test_argmax_decodes_of_equivalent_rotations_are_one_pose_within_the_grid_tolerance(n_axes, n_angles):
    """The argmax decode of R S_k is ``same_pose`` as that of R within one grid step; half a step is too
    tight (equivalents of a grid rotation are off the grid), and a non-symmetry rotation is another pose."""
    rng = np.random.default_rng(27)
    layout = CodeLayout(n_axes=n_axes, n_angles=n_angles)
    pc, tolerance = PopulationCode(layout), argmax_tolerance_rad(layout)
    assert np.degrees(tolerance) == pytest.approx(np.hypot(360 / n_angles, 2 * np.degrees(np.sqrt(4 * np.pi / n_axes))))
    S = symmetry_rotations(CASES["four_fold"])
    R = random_rotations(200, rng)
    decoded = np.stack([pc.decode(pc.encode(R @ s)).R for s in S], axis=1)  # (N, 4, 3, 3)
    same = [same_pose(layout, d[k], d[0], S, tolerance) for d in decoded for k in range(1, 4)]
    assert all(same)
    assert not all(same_pose(layout, d[k], d[0], S, tolerance / 2) for d in decoded for k in range(1, 4))
    quarter_turn_x = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.pi / 2)  # not a symmetry
    other = pc.decode(pc.encode(R @ quarter_turn_x)).R
    assert not any(same_pose(layout, o, d[0], S, tolerance) for o, d in zip(other, decoded, strict=True))


def test_axis_only_argmax_decodes_compare_the_symmetry_axis():
    rng = np.random.default_rng(28)
    layout = CodeLayout(n_axes=642, axis_only=True, symmetry_axis=(0.0, 0.0, 1.0))
    pc, tolerance = PopulationCode(layout), argmax_tolerance_rad(layout)
    S = symmetry_rotations(CASES["continuous_flip"])
    R = random_rotations(300, rng)
    spin = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), 1.0)  # about the symmetry axis: the same pose
    plain, flipped = pc.decode(pc.encode(R)).R, pc.decode(pc.encode(R @ S[1] @ spin)).R
    assert all(same_pose(layout, f, p, S, tolerance) for f, p in zip(flipped, plain, strict=True))
    assert not any(same_pose(layout, f, p, S[:1], tolerance) for f, p in zip(flipped, plain, strict=True))


@pytest.mark.parametrize("bad,message", [(np.zeros, "flat"), (np.ones, "flat")])
def test_degenerate_codes_are_refused(bad, message):
    pc = PopulationCode(CodeLayout(n_axes=162, n_angles=12))
    with pytest.raises(PopcodeError, match=message):
        find_hypotheses(pc, bad(pc.layout.size, dtype=np.float32))
    nan_code = np.full(pc.layout.size, np.nan, np.float32)
    with pytest.raises(PopcodeError, match="NaN"):
        decode_refined(pc, nan_code)


def test_refined_decoder_only_for_population_codes():
    meta = ModelMetadata(representation=Representation.SINGLE_VARIABLE, code=CodeLayout(n_axes=42, n_angles=6),
                         objects={1: CASES["none"]})
    with pytest.raises(PopcodeError, match="population-code"):
        decode_output(np.ones((1, 6)), meta, decoder="refined")
    with pytest.raises(PopcodeError, match="unknown decoder"):
        decode_output(np.ones((1, 6)), meta, decoder="magic")


def projected_box(points_cam):
    """The BOP box of the points' silhouette."""
    uv = project_camera_points(points_cam, K)
    return box_from_edges([*uv.min(axis=0), *uv.max(axis=0)])


def test_a_bop_box_spans_half_a_pixel_beyond_its_first_and_last_pixel_centres():
    # Pixels 10..29 across and 5..6 down: the BOP toolkit's box is (10, 5, 19, 1), the silhouette 9.5..29.5, 4.5..6.5.
    assert box_edges([10, 5, 19, 1]).tolist() == [9.5, 4.5, 29.5, 6.5]
    assert box_from_edges(box_edges([10.25, 5, 19, 1.5])) == (10.25, 5, 19, 1.5)


def test_translation_from_the_exact_box_of_the_hull():
    """With the same points that made the box, the translation is recovered to 1e-6 of the distance."""
    rng = np.random.default_rng(27)
    points = rng.normal(size=(300, 3)) * [40.0, 25.0, 15.0]
    for R in random_rotations(20, rng):
        t = np.array([rng.uniform(-150, 150), rng.uniform(-100, 100), rng.uniform(300, 1500)])
        estimate = translation_from_box(R, projected_box(points @ R.T + t), K, points)
        assert np.linalg.norm(estimate - t) < 1e-6 * t[2]


def test_translation_with_box_corners_only_overestimates_distance():
    rng = np.random.default_rng(28)
    info = CASES["none"]
    points = object_points_mm(info)
    assert points.shape == (8, 3)
    # A sphere-ish object inside the 3-D box: its true silhouette is smaller than the box corners'.
    surface = rng.normal(size=(400, 3))
    surface = surface / np.linalg.norm(surface, axis=1, keepdims=True) * 30.0
    R = random_rotations(1, rng)[0]
    t = np.array([20.0, -10.0, 800.0])
    estimate = translation_from_box(R, projected_box(surface @ R.T + t), K, points)
    assert estimate[2] > t[2]
    assert np.linalg.norm(np.cross(estimate, t)) / (np.linalg.norm(estimate) * np.linalg.norm(t)) < 1e-2


def test_estimator_top_k_translation_and_refined(tmp_path):
    rng = np.random.default_rng(29)
    layout = CodeLayout(n_axes=642, n_angles=36)
    info = {**CASES["two_fold"], "hull_points_mm": (rng.normal(size=(50, 3)) * 30).tolist()}
    S = symmetry_rotations(info)
    R = random_rotations(1, rng)[0]
    meta = ModelMetadata(representation=Representation.POPULATION_CODE, code=layout, objects={4: info})
    model = save(linear_model(PopulationCode(layout).encode(R, S), metadata=meta), tmp_path / "m.onnx")
    scene = np.zeros((540, 720), np.uint8)
    t_true = np.array([30.0, -20.0, 700.0])
    box = projected_box(np.asarray(info["hull_points_mm"]) @ R.T + t_true)
    box_symmetric = projected_box(np.asarray(info["hull_points_mm"]) @ (R @ S[1]).T + t_true)
    argmax = PoseEstimator(model).predict(scene, [box])[0]
    refined_estimator = PoseEstimator(model, decoder="refined")
    refined = refined_estimator.predict(scene, [box], K=K, top_k=3, translation=True)[0]
    assert geodesic_angle(refined.R_m2c, R @ S).min() < geodesic_angle(argmax.R_m2c, R @ S).min()
    assert refined.obj_id == 4 and len(refined.hypotheses) == 1 and len(refined.hypotheses[0].equivalent) == 2
    # The refined rotation is one of the two symmetric poses; the box was drawn with that pose.
    pose = int(np.argmin(geodesic_angle(refined.R_m2c, R @ S)))
    if pose == 1:
        refined = refined_estimator.predict(scene, [box_symmetric], K=K, translation=True)[0]
    assert np.linalg.norm(refined.t_m2c_mm - t_true) < 0.01 * t_true[2]
    with pytest.raises(PopcodeError, match="camera matrix K"):
        refined_estimator.predict(scene, [box], translation=True)
    with pytest.raises(PopcodeError, match="not in this model"):
        refined_estimator.predict(scene, [box], obj_ids=[99])
