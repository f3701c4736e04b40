import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from popcode_runtime.geometry import rotations as rot

N = 500


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def scipy_rotations(rng):
    return Rotation.random(N, random_state=rng)


def test_axis_angle_to_matrix_matches_scipy(scipy_rotations):
    rotvec = scipy_rotations.as_rotvec()
    angle = np.linalg.norm(rotvec, axis=1)
    R = rot.axis_angle_to_matrix(rotvec / angle[:, None], angle)
    np.testing.assert_allclose(R, scipy_rotations.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(rot.rotvec_to_matrix(rotvec), scipy_rotations.as_matrix(), atol=1e-12)


def test_matrix_to_axis_angle_matches_scipy(scipy_rotations):
    axis, angle = rot.matrix_to_axis_angle(scipy_rotations.as_matrix())
    np.testing.assert_allclose(axis * angle[:, None], scipy_rotations.as_rotvec(), atol=1e-9)
    assert np.all((angle >= 0) & (angle <= np.pi))
    np.testing.assert_allclose(np.linalg.norm(axis, axis=1), 1.0, atol=1e-12)


def test_axis_angle_near_zero_and_pi():
    axis = np.array([[0.0, 0.6, 0.8]] * 4)
    angles = np.array([0.0, 1e-9, np.pi - 1e-9, np.pi])
    back_axis, back_angle = rot.matrix_to_axis_angle(rot.axis_angle_to_matrix(axis, angles))
    np.testing.assert_allclose(back_angle, angles, atol=1e-7)
    # Near pi the axis is defined up to sign; away from 0 it must match.
    np.testing.assert_allclose(np.abs(back_axis[2:] @ axis[0]), 1.0, atol=1e-6)


def test_quaternion_conversions_match_scipy(scipy_rotations):
    q = rot.matrix_to_quaternion(scipy_rotations.as_matrix())
    expected = scipy_rotations.as_quat()
    expected = np.where(expected[:, 3:4] < 0, -expected, expected)
    np.testing.assert_allclose(q, expected, atol=1e-12)
    np.testing.assert_allclose(rot.quaternion_to_matrix(expected * 3.0), scipy_rotations.as_matrix(), atol=1e-12)


def test_sixd_round_trip_and_gram_schmidt(scipy_rotations, rng):
    R = scipy_rotations.as_matrix()
    np.testing.assert_allclose(rot.sixd_to_matrix(rot.matrix_to_sixd(R)), R, atol=1e-12)
    noisy = rot.matrix_to_sixd(R) + rng.normal(scale=0.1, size=(N, 6))
    out = rot.sixd_to_matrix(noisy)
    np.testing.assert_allclose(out @ np.swapaxes(out, 1, 2), np.broadcast_to(np.eye(3), out.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(out), 1.0, atol=1e-12)
    # The first column keeps the direction of the first 3 numbers.
    first = noisy[:, :3] / np.linalg.norm(noisy[:, :3], axis=1, keepdims=True)
    np.testing.assert_allclose(out[:, :, 0], first, atol=1e-12)


def test_geodesic_angle_matches_scipy_and_is_accurate_near_zero(rng):
    a, b = Rotation.random(N, random_state=rng), Rotation.random(N, random_state=rng)
    expected = (a.inv() * b).magnitude()
    np.testing.assert_allclose(rot.geodesic_angle(a.as_matrix(), b.as_matrix()), expected, atol=1e-9)
    tiny = Rotation.from_rotvec([1e-7, 0, 0]).as_matrix()
    assert rot.geodesic_angle(np.eye(3), tiny) == pytest.approx(1e-7, rel=1e-6)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_functions_accept_float32_and_float64(scipy_rotations, dtype):
    R = scipy_rotations.as_matrix().astype(dtype)
    back = rot.quaternion_to_matrix(rot.matrix_to_quaternion(R))
    np.testing.assert_allclose(back, R, atol=1e-6 if dtype == np.float32 else 1e-12)


def test_rotation_between_is_minimal(rng):
    a = rng.normal(size=(N, 3))
    b = rng.normal(size=(N, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    R = rot.rotation_between(a, b)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", R, a), b, atol=1e-12)
    _, angle = rot.matrix_to_axis_angle(R)
    np.testing.assert_allclose(angle, np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)), atol=1e-7)


def test_rotation_between_parallel_and_antiparallel():
    z = np.array([0.0, 0.0, 1.0])
    np.testing.assert_allclose(rot.rotation_between(z, z), np.eye(3), atol=1e-12)
    flip = rot.rotation_between(z, -z)
    np.testing.assert_allclose(flip @ z, -z, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(flip), 1.0, atol=1e-12)


def test_egocentric_allocentric_round_trip_and_ray(scipy_rotations, rng):
    K = np.array([[1075.6, 0.0, 360.0], [0.0, 1073.9, 270.0], [0.0, 0.0, 1.0]])
    pixels = rng.uniform([0, 0], [720, 540], size=(N, 2))
    R_ego = scipy_rotations.as_matrix()
    R_allo = rot.egocentric_to_allocentric(R_ego, K, pixels)
    np.testing.assert_allclose(rot.allocentric_to_egocentric(R_allo, K, pixels), R_ego, atol=1e-12)
    # The ray rotation takes the optical axis to the ray through the pixel.
    R_ray = rot.ray_rotation(K, pixels)
    ray = np.linalg.solve(K, np.c_[pixels, np.ones(N)].T).T
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    np.testing.assert_allclose(R_ray[:, :, 2], ray, atol=1e-12)
    # On the optical axis the two frames agree.
    np.testing.assert_allclose(rot.egocentric_to_allocentric(R_ego[:3], K, [[360.0, 270.0]] * 3), R_ego[:3],
                               atol=1e-12)


def test_random_rotations_are_uniform(rng):
    R = rot.random_rotations(20000, rng)
    # For uniform rotations, E[trace] = 1 + 2 E[cos angle] = 0 and each column is uniform on the sphere.
    assert abs(np.trace(R, axis1=1, axis2=2).mean()) < 0.05
    assert np.abs(R[:, :, 2].mean(axis=0)).max() < 0.03


def test_is_rotation_takes_rotations_only(scipy_rotations):
    assert all(rot.is_rotation(R) for R in scipy_rotations.as_matrix())
    assert all(rot.is_rotation(R.astype(np.float32)) for R in scipy_rotations.as_matrix())
    R = scipy_rotations.as_matrix()[0]
    for wrong in (-R, R * 1.001, np.diag([1.0, 1.0, 2.0]), np.where(np.eye(3) > 0, np.nan, R), R[:2], np.eye(4)):
        assert not rot.is_rotation(wrong)
