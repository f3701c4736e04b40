"""Point projection: the one definition agrees with OpenCV's and puts the optical axis on the principal point."""

import cv2
import numpy as np

from popcode_runtime.geometry.camera import project_camera_points, project_points
from popcode_runtime.geometry.rotations import random_rotations

K = np.array([[612.3, 0.0, 319.7], [0.0, 608.9, 241.2], [0.0, 0.0, 1.0]])


def test_a_point_on_the_optical_axis_lands_on_the_principal_point() -> None:
    uv = project_camera_points(np.array([[0.0, 0.0, 750.0]]), K)
    np.testing.assert_allclose(uv, [[K[0, 2], K[1, 2]]], atol=1e-12)


def test_projection_matches_opencv() -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform(-60.0, 60.0, size=(50, 3))
    for R in random_rotations(5, rng):
        t = np.array([*rng.uniform(-100.0, 100.0, 2), rng.uniform(400.0, 900.0)])
        expected, _ = cv2.projectPoints(points, cv2.Rodrigues(R)[0], t, K, None)
        np.testing.assert_allclose(project_points(points, K, R, t), expected[:, 0], atol=1e-9)


def test_batched_camera_points_keep_their_leading_shape() -> None:
    points = np.random.default_rng(4).uniform(-50.0, 50.0, size=(2, 7, 3)) + [0.0, 0.0, 500.0]
    uv = project_camera_points(points, K)
    assert uv.shape == (2, 7, 2)
    np.testing.assert_allclose(uv[1], project_camera_points(points[1], K))
