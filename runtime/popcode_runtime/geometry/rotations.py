"""Rotation maths on numpy arrays, vectorised over leading batch dimensions.

Conventions (the same everywhere in popcode):
- rotation matrices act on column vectors, shape ``(..., 3, 3)``;
- axis/angle: unit axis ``(..., 3)`` and angle in radians ``(...)``, angle in [0, pi];
- quaternions are scalar-last ``(x, y, z, w)``, as in ``scipy.spatial.transform``;
- the 6-D representation is the first two columns of R, stacked as ``(c1, c2)``;
- camera frame is OpenCV's: x right, y down, z forward.
"""

from __future__ import annotations

import numpy as np

_EPS = 1e-12


def _normalize(v: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(norm, _EPS)


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v]x`` of ``(..., 3)`` vectors, shape ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=np.float64)
    zero = np.zeros(v.shape[:-1])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(
        [
            np.stack([zero, -z, y], axis=-1),
            np.stack([z, zero, -x], axis=-1),
            np.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )


def axis_angle_to_matrix(axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: unit axis ``(..., 3)`` and angle ``(...)`` -> ``(..., 3, 3)``."""
    axis = _normalize(np.asarray(axis, dtype=np.float64))
    angle = np.asarray(angle_rad, dtype=np.float64)[..., None, None]
    k = skew(axis)
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation vector (axis times angle, ``(..., 3)``) -> ``(..., 3, 3)``."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    return axis_angle_to_matrix(rotvec, np.linalg.norm(rotvec, axis=-1))


def matrix_to_axis_angle(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(..., 3, 3)`` -> (unit axis ``(..., 3)``, angle ``(...)`` in [0, pi]).

    Goes through the quaternion, which stays accurate near 0 and pi where the
    trace formula does not. For the identity the axis is arbitrary (+z).
    """
    q = matrix_to_quaternion(R)
    xyz, w = q[..., :3], q[..., 3]
    # Use the hemisphere w >= 0 so that the angle lies in [0, pi].
    sign = np.where(w < 0, -1.0, 1.0)
    xyz, w = xyz * sign[..., None], w * sign
    sin_half = np.linalg.norm(xyz, axis=-1)
    angle = 2.0 * np.arctan2(sin_half, w)
    axis = np.where(
        sin_half[..., None] > 1e-9, xyz / np.maximum(sin_half, _EPS)[..., None], [0.0, 0.0, 1.0]
    )
    return axis, angle


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternion ``(..., 4)`` scalar-last ``(x, y, z, w)``, any norm > 0 -> ``(..., 3, 3)``."""
    q = _normalize(np.asarray(q, dtype=np.float64))
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` -> unit quaternion ``(..., 4)`` ``(x, y, z, w)`` with ``w >= 0``.

    Shepperd's method: picks the numerically largest of the four candidate
    components per matrix, so it is stable for every rotation.
    """
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    trace = m00 + m11 + m22
    candidates = np.stack([trace, m00, m11, m22], axis=-1)
    choice = np.argmax(candidates, axis=-1)

    q = np.empty(R.shape[:-2] + (4,))
    # w largest
    s = np.sqrt(np.maximum(1.0 + trace, _EPS)) * 2.0
    q_w = np.stack(
        [(R[..., 2, 1] - R[..., 1, 2]) / s, (R[..., 0, 2] - R[..., 2, 0]) / s,
         (R[..., 1, 0] - R[..., 0, 1]) / s, 0.25 * s], -1)
    # x largest
    s = np.sqrt(np.maximum(1.0 + m00 - m11 - m22, _EPS)) * 2.0
    q_x = np.stack(
        [0.25 * s, (R[..., 0, 1] + R[..., 1, 0]) / s,
         (R[..., 0, 2] + R[..., 2, 0]) / s, (R[..., 2, 1] - R[..., 1, 2]) / s], -1)
    # y largest
    s = np.sqrt(np.maximum(1.0 - m00 + m11 - m22, _EPS)) * 2.0
    q_y = np.stack(
        [(R[..., 0, 1] + R[..., 1, 0]) / s, 0.25 * s,
         (R[..., 1, 2] + R[..., 2, 1]) / s, (R[..., 0, 2] - R[..., 2, 0]) / s], -1)
    # z largest
    s = np.sqrt(np.maximum(1.0 - m00 - m11 + m22, _EPS)) * 2.0
    q_z = np.stack(
        [(R[..., 0, 2] + R[..., 2, 0]) / s, (R[..., 1, 2] + R[..., 2, 1]) / s,
         0.25 * s, (R[..., 1, 0] - R[..., 0, 1]) / s], -1)
    for index, candidate in enumerate((q_w, q_x, q_y, q_z)):
        mask = choice == index
        q[mask] = candidate[mask]
    q = _normalize(q)
    return np.where(q[..., 3:4] < 0, -q, q)


def sixd_to_matrix(sixd: np.ndarray) -> np.ndarray:
    """6-D representation ``(..., 6)`` = first two columns -> ``(..., 3, 3)`` by Gram-Schmidt."""
    sixd = np.asarray(sixd, dtype=np.float64)
    c1 = _normalize(sixd[..., 0:3])
    c2 = sixd[..., 3:6]
    c2 = _normalize(c2 - np.sum(c1 * c2, axis=-1, keepdims=True) * c1)
    c3 = np.cross(c1, c2)
    return np.stack([c1, c2, c3], axis=-1)


def matrix_to_sixd(R: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` -> its first two columns as ``(..., 6)``."""
    R = np.asarray(R, dtype=np.float64)
    return np.concatenate([R[..., :, 0], R[..., :, 1]], axis=-1)


def geodesic_angle(R1: np.ndarray, R2: np.ndarray) -> np.ndarray:
    """Angle in radians of ``R1^T R2``, accurate near 0 (``2 asin(|R2 - R1|_F / sqrt 8)``)."""
    diff = np.asarray(R2, dtype=np.float64) - np.asarray(R1, dtype=np.float64)
    chord = np.linalg.norm(diff, axis=(-2, -1)) / (2.0 * np.sqrt(2.0))
    return 2.0 * np.arcsin(np.clip(chord, 0.0, 1.0))


def is_rotation(R: np.ndarray, atol: float = 1e-5) -> bool:
    """Whether ``R`` is one rotation matrix ``(3, 3)``: finite, orthonormal within ``atol``, determinant +1 (a
    reflection is none)."""
    R = np.asarray(R, dtype=np.float64)
    return bool(R.shape == (3, 3) and np.isfinite(R).all() and np.allclose(R @ R.T, np.eye(3), atol=atol)
                and np.linalg.det(R) > 0)


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Minimal rotation taking unit vector ``a`` to unit vector ``b`` (both ``(..., 3)``).

    For antiparallel vectors the rotation is by pi about an axis orthogonal to
    ``a``, chosen deterministically.
    """
    a = _normalize(np.asarray(a, dtype=np.float64))
    b = _normalize(np.asarray(b, dtype=np.float64))
    a, b = np.broadcast_arrays(a, b)
    cross = np.cross(a, b)
    sin = np.linalg.norm(cross, axis=-1)
    cos = np.sum(a * b, axis=-1)
    angle = np.arctan2(sin, cos)
    # Fallback axis for (anti)parallel vectors: orthogonal to a.
    helper = np.where(np.abs(a[..., 0:1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    fallback = _normalize(np.cross(a, helper))
    axis = np.where(sin[..., None] > 1e-9, cross / np.maximum(sin, _EPS)[..., None], fallback)
    return axis_angle_to_matrix(axis, angle)


def ray_rotation(K: np.ndarray, pixel_xy: np.ndarray) -> np.ndarray:
    """Minimal rotation taking the camera z-axis to the ray through ``pixel_xy``.

    ``K`` is a 3x3 camera matrix (shared or ``(..., 3, 3)``), ``pixel_xy`` is
    ``(..., 2)`` in pixels. Returns ``R_ray`` of shape ``(..., 3, 3)``.
    """
    K = np.asarray(K, dtype=np.float64)
    pixel_xy = np.asarray(pixel_xy, dtype=np.float64)
    homogeneous = np.concatenate([pixel_xy, np.ones(pixel_xy.shape[:-1] + (1,))], axis=-1)
    ray = np.linalg.solve(K, homogeneous[..., None])[..., 0]
    return rotation_between(np.array([0.0, 0.0, 1.0]), ray)


def egocentric_to_allocentric(R_ego: np.ndarray, K: np.ndarray, pixel_xy: np.ndarray) -> np.ndarray:
    """``R_allo = R_ray^T R_ego``: the rotation as seen in a crop centred on ``pixel_xy``."""
    return np.swapaxes(ray_rotation(K, pixel_xy), -1, -2) @ np.asarray(R_ego, dtype=np.float64)


def allocentric_to_egocentric(R_allo: np.ndarray, K: np.ndarray, pixel_xy: np.ndarray) -> np.ndarray:
    """``R_ego = R_ray R_allo``: back to the camera frame (inverse of the above)."""
    return ray_rotation(K, pixel_xy) @ np.asarray(R_allo, dtype=np.float64)


def random_rotations(count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` rotations uniform on SO(3) (normalised Gaussian quaternions)."""
    return quaternion_to_matrix(rng.normal(size=(count, 4)))
