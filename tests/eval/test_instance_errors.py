"""Per-instance errors of a whole split, as the evaluate command computes them."""

from __future__ import annotations

import numpy as np
import pytest
from box_render import box_depth_renderer
from symmetry_cases import CASES

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, random_rotations
from popcode_trainer.eval.pipeline.instance_errors import ObjectModel, compute_instance_errors
from popcode_trainer.metrics.pose_errors import mspd
from popcode_trainer.metrics.recall import metric_scores

HALF_MM = {1: np.array([40.0, 25.0, 10.0]), 2: np.array([30.0, 30.0, 20.0])}
INFO = {1: CASES["none"], 2: CASES["four_fold"]}
WIDTH, HEIGHT = 160, 120
K1 = np.array([[600.0, 0.0, 80.0], [0.0, 600.0, 60.0], [0.0, 0.0, 1.0]])
K2 = np.array([[650.0, 0.0, 79.5], [0.0, 650.0, 59.5], [0.0, 0.0, 1.0]])


def _models() -> dict[int, ObjectModel]:
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    return {obj: ObjectModel.from_info(HALF_MM[obj] * corners, INFO[obj]) for obj in (1, 2)}


def _make_render(obj_id: int, K: np.ndarray, width: int, height: int):
    return box_depth_renderer(HALF_MM[obj_id], K, width, height)


def _split(rng: np.random.Generator):
    obj_id = np.array([1, 1, 2, 2])
    R_gt = random_rotations(4, rng)
    t_gt = np.tile([0.0, 0.0, 800.0], (4, 1))
    K = np.stack([K1, K2, K1, K2])
    depth = [_make_render(int(o), k, WIDTH, HEIGHT)(R, t) for o, k, R, t in zip(obj_id, K, R_gt, t_gt, strict=True)]
    return obj_id, R_gt, t_gt, K, depth


def test_perfect_estimates_score_one_everywhere():
    obj_id, R_gt, t_gt, K, depth = _split(np.random.default_rng(0))
    models = _models()
    errors = compute_instance_errors(obj_id, R_gt, R_gt, t_gt, K, np.full(4, WIDTH), models,
                                     depth_mm=depth, make_render_depth=_make_render)
    np.testing.assert_allclose(errors.mssd_mm, 0.0, atol=1e-9)
    np.testing.assert_array_equal(errors.vsd, 0.0)
    scores = metric_scores(errors, {o: m.diameter_mm for o, m in models.items()})
    assert scores == {name: 1.0 for name in ("VSD", "MSSD", "MSPD", "e_VSD<0.3", "VSS", "ADI")}


def test_errors_match_the_single_functions_with_per_instance_cameras():
    obj_id, R_gt, t_gt, K, depth = _split(np.random.default_rng(1))
    models = _models()
    turn = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), np.radians(30.0))
    R_est = turn @ R_gt
    errors = compute_instance_errors(obj_id, R_est, R_gt, t_gt, K, np.full(4, WIDTH), models,
                                     depth_mm=depth, make_render_depth=_make_render)
    for i in range(4):
        model = models[int(obj_id[i])]
        expected = mspd(R_est[i], t_gt[i], R_gt[i], t_gt[i], K[i], model.pts_mm, model.syms)
        assert errors.mspd_px[i] == pytest.approx(float(expected))
    assert np.all(errors.vss <= errors.vsd_single_tau) and np.all(errors.vsd > 0)


def test_estimated_translations_replace_the_truth_in_every_error():
    obj_id, R_gt, t_gt, K, depth = _split(np.random.default_rng(4))
    models = _models()
    t_est = t_gt + np.array([3.0, -4.0, 0.0])  # 5 mm sideways
    errors = compute_instance_errors(obj_id, R_gt, R_gt, t_gt, K, np.full(4, WIDTH), models,
                                     depth_mm=depth, make_render_depth=_make_render, t_est_mm=t_est)
    # Box corners are centrally symmetric, so a pure shift's MSSD is its length under every symmetry.
    np.testing.assert_allclose(errors.mssd_mm, 5.0)
    for i in range(4):
        model = models[int(obj_id[i])]
        expected = mspd(R_gt[i], t_est[i], R_gt[i], t_gt[i], K[i], model.pts_mm, model.syms)
        assert errors.mspd_px[i] == pytest.approx(float(expected)) and errors.mspd_px[i] > 3.0
    assert np.all(errors.vsd[:, 0] > 0)  # the shifted silhouette no longer covers the true one


def test_without_depth_the_depth_metrics_are_skipped_with_a_warning():
    obj_id, R_gt, t_gt, K, _ = _split(np.random.default_rng(2))
    with pytest.warns(UserWarning, match="VSD"):
        errors = compute_instance_errors(obj_id, R_gt, R_gt, t_gt, K, np.full(4, WIDTH), _models())
    assert errors.vsd is None and errors.vss is None and errors.vsd_single_tau is None


def test_bad_inputs_are_reported():
    obj_id, R_gt, t_gt, K, depth = _split(np.random.default_rng(3))
    models = _models()
    with pytest.raises(PopcodeError, match="no object model for object ids \\[9\\]"):
        compute_instance_errors(np.array([1, 1, 2, 9]), R_gt, R_gt, t_gt, K, np.full(4, WIDTH), models)
    with pytest.raises(PopcodeError, match="differ in length"):
        compute_instance_errors(obj_id, R_gt[:3], R_gt, t_gt, K, np.full(4, WIDTH), models)
    with pytest.raises(PopcodeError, match="depth renderer"):
        compute_instance_errors(obj_id, R_gt, R_gt, t_gt, K, np.full(4, WIDTH), models, depth_mm=depth)
