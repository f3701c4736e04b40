"""The pinhole camera, in OpenCV's convention: ``K`` 3x3, x right, y down, z forward, pixel centres at integers.

One definition of the camera matrix's parsing and of point projection for the
runtime (box fitting), the renderer and the BOP metrics (MSPD).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..base.errors import PopcodeError

MAX_FOCAL_PX = 1e6  # a 1000 mm lens on 1 um pixels; beyond this the numbers are not a camera
MAX_PRINCIPAL_PX = 1e6
# A depth camera's unit (BOP's depth_scale: mm = value x depth_scale), kept with the camera it belongs to:
# 0.1 um (a float depth in nm) to 10 m.
MIN_DEPTH_SCALE, MAX_DEPTH_SCALE = 1e-4, 1e4


def parse_camera_matrix(values: Sequence[float] | np.ndarray) -> np.ndarray:
    """A camera matrix from ``(fx, fy, cx, cy)``, 9 row-major numbers or a 3x3 array.

    The numbers must be finite and physical: focal lengths in (0, 1e6] px,
    principal point and skew within 1e6 px, last row ``0 0 1``.
    """
    if isinstance(values, (str, bytes)):
        raise PopcodeError(f"a camera matrix is numbers, not the text {values!r}")
    try:
        K = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as error:
        raise PopcodeError("a camera matrix is fx,fy,cx,cy, 9 numbers or a 3x3 array of numbers") from error
    if K.shape == (4,):
        fx, fy, cx, cy = K
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    elif K.shape in ((9,), (3, 3)):
        K = K.reshape(3, 3)
    else:
        raise PopcodeError(f"a camera matrix is fx,fy,cx,cy, 9 numbers or 3x3; got shape {K.shape}")
    if not np.isfinite(K).all():
        raise PopcodeError("camera matrix contains NaN or inf")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise PopcodeError(f"not a valid camera matrix (focal lengths must be positive, last row 0 0 1): {K.tolist()}")
    if max(K[0, 0], K[1, 1]) > MAX_FOCAL_PX or np.abs(K[:2, 1:]).max() > MAX_PRINCIPAL_PX or K[1, 0] != 0.0:
        raise PopcodeError(f"camera matrix is not physical (focal lengths at most {MAX_FOCAL_PX:g} px, principal "
                           f"point and skew within {MAX_PRINCIPAL_PX:g} px, K[1][0] = 0): {K.tolist()}")
    if abs(np.linalg.det(K)) < 1e-12:
        raise PopcodeError(f"not a valid camera matrix (it is singular): {K.tolist()}")
    return K


def project_camera_points(points_c_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``(..., 2)`` [px] of camera-frame points ``(..., 3)`` [mm] (in front of the camera)."""
    uvw = np.asarray(points_c_mm) @ np.asarray(K).T
    return uvw[..., :2] / uvw[..., 2:3]


def project_points(points_m_mm: np.ndarray, K: np.ndarray, R_m2c: np.ndarray, t_m2c_mm: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``(N, 2)`` [px] of model points ``(N, 3)`` [mm] seen in the pose ``x_c = R x_m + t``."""
    return project_camera_points(np.asarray(points_m_mm) @ np.asarray(R_m2c).T + np.asarray(t_m2c_mm), K)
