"""Translation from the detected box: where must the rotated object sit so that it fills the box?

The paper takes the translation from the ground truth; a robot has only the
image and the box. Given the rotation, the camera matrix and points on the
object's hull (from the model metadata, so no mesh is needed on the device),
the translation is the one whose projected points' bounding box matches the
detected box, solved by Gauss-Newton on the four box edges.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ..base.errors import PopcodeError
from .camera import project_camera_points
from .crop import box_centre, box_edges


def object_points_mm(info: Mapping[str, Any]) -> np.ndarray:
    """Points ``(P, 3)`` [mm] that bound the object: ``hull_points_mm`` if the metadata has them,
    else the 8 corners of the BOP 3-D box (``min_x`` ... ``size_z``), which overestimate the
    silhouette and so bias the distance slightly high."""
    if "hull_points_mm" in info:
        try:
            points = np.asarray(info["hull_points_mm"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            points = np.empty(0)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 4 or not np.isfinite(points).all():
            raise PopcodeError("hull_points_mm must be a list of at least 4 finite points [x, y, z]")
        if np.linalg.matrix_rank(points - points.mean(axis=0), tol=1e-6 * max(np.abs(points).max(), 1.0)) < 3:
            raise PopcodeError("hull_points_mm are degenerate: they must span a volume, not a point, line or plane")
        return points
    try:
        low = np.array([info["min_x"], info["min_y"], info["min_z"]], dtype=np.float64)
        size = np.array([info["size_x"], info["size_y"], info["size_z"]], dtype=np.float64)
    except KeyError as error:
        raise PopcodeError(f"object metadata lacks {error.args[0]!r}: no extents to place the object") from error
    except (TypeError, ValueError, OverflowError) as error:
        raise PopcodeError("object extents (min_x ... size_z) must be numbers") from error
    if not (np.isfinite(low).all() and np.isfinite(size).all() and (size > 0).all()):
        raise PopcodeError(f"object extents must be finite with positive sizes, got size {size.tolist()}")
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=np.float64)
    return low + corners * size


def _box_of(points_cam: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Box edges ``(x_min, y_min, x_max, y_max)`` [px] of camera-frame points."""
    uv = project_camera_points(points_cam, K)
    return np.concatenate([uv.min(axis=0), uv.max(axis=0)])


def _box_and_jacobian(points_cam: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Box edges ``(4,)`` [px] of camera-frame points and their derivatives ``(4, 3)`` by the translation.

    Each edge moves with the point that makes it, so its derivative is that
    point's projection's: ``u = (fx X + s Y) / Z + cx`` and ``v = fy Y / Z + cy``.
    One projection per step instead of seven for central differences.
    """
    uv = project_camera_points(points_cam, K)
    extremes = np.concatenate([uv.argmin(axis=0), uv.argmax(axis=0)])
    coordinate = np.array([0, 1, 0, 1])
    X, Y, Z = points_cam[extremes].T
    jacobian = np.zeros((4, 3))
    u_rows, v_rows = coordinate == 0, coordinate == 1
    jacobian[u_rows, 0] = K[0, 0] / Z[u_rows]
    jacobian[u_rows, 1] = K[0, 1] / Z[u_rows]
    jacobian[u_rows, 2] = -(K[0, 0] * X[u_rows] + K[0, 1] * Y[u_rows]) / Z[u_rows] ** 2
    jacobian[v_rows, 1] = K[1, 1] / Z[v_rows]
    jacobian[v_rows, 2] = -K[1, 1] * Y[v_rows] / Z[v_rows] ** 2
    return uv[extremes, coordinate], jacobian


def translation_from_box(
    R_m2c: np.ndarray, box: Sequence[float], K: np.ndarray, points_mm: np.ndarray, iterations: int = 30
) -> np.ndarray:
    """Translation ``(3,)`` [mm] placing ``points_mm`` (rotated by ``R_m2c``) to fill ``box`` (x, y, w, h px, BOP)."""
    target = box_edges(box)
    rotated = points_mm @ np.asarray(R_m2c, dtype=np.float64).T
    # Start on the ray through the box centre, at the distance where the object's spread fits the box.
    spread_mm = np.ptp(rotated[:, :2], axis=0).max()
    if spread_mm <= 0.0:
        raise PopcodeError("the object's points have no extent across the view; no distance fills the box")
    focal = (K[0, 0] + K[1, 1]) / 2.0
    distance = focal * spread_mm / (target[2:] - target[:2]).max()
    ray = np.linalg.solve(K, np.append(box_centre(box), 1.0))
    t = ray / ray[2] * distance
    for _ in range(iterations):
        if np.min(rotated[:, 2] + t[2]) <= 1e-6:
            t[2] = -rotated[:, 2].min() + 1.0  # keep every point in front of the camera
        edges, jacobian = _box_and_jacobian(rotated + t, K)
        residual = edges - target
        if not (np.isfinite(jacobian).all() and np.isfinite(residual).all()):
            break  # LAPACK may not return on NaN; the check below refuses the result
        update, *_ = np.linalg.lstsq(jacobian, -residual, rcond=None)
        t = t + update
        if np.linalg.norm(update) < 1e-6 * abs(t[2]):
            break
    if not (np.isfinite(t).all() and np.isfinite(_box_of(rotated + t, K)).all()) or t[2] <= 0:
        raise PopcodeError(f"no translation places the object in box {list(box)}")
    return t
