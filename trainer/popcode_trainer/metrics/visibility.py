"""Distance images and the BOP toolkit's visibility estimation (its ``bop19`` mode).

Depth images hold the z coordinate in mm of the surface seen at each pixel (0 where
nothing is seen); distance images hold the distance in mm from the camera centre.
VSD compares distance images, never depth images.
"""

from __future__ import annotations

import numpy as np

from popcode_runtime.base.errors import PopcodeError


def depth_to_distance(depth_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth image ``(H, W)`` [mm] -> distance image ``(H, W)`` [mm] from the camera centre.

    ``K`` is the 3x3 intrinsic matrix (OpenCV convention, pixel centres at integer
    coordinates). Pixels with depth 0 stay 0.
    """
    depth = np.asarray(depth_mm, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    height, width = depth.shape
    x_over_z = (np.arange(width) - K[0, 2]) / K[0, 0]
    y_over_z = (np.arange(height) - K[1, 2]) / K[1, 1]
    return depth * np.sqrt(1.0 + x_over_z[None, :] ** 2 + y_over_z[:, None] ** 2)


def _visible(dist_test: np.ndarray, dist_model: np.ndarray, delta_mm: float) -> np.ndarray:
    """Pixels where the rendered model is not behind the scene by more than ``delta_mm``.

    Missing scene depth (0) counts as visible, so shiny objects that the sensor
    misses can still be evaluated (the toolkit's ``bop19`` mode). The difference is
    taken in float32 as the toolkit does, so that pixels at the tolerance agree.
    """
    if dist_test.shape != dist_model.shape:
        raise PopcodeError(f"test image {dist_test.shape} and rendering {dist_model.shape} differ in size")
    diff = dist_model.astype(np.float32) - dist_test.astype(np.float32)
    return ((diff <= delta_mm) | (dist_test == 0)) & (dist_model > 0)


def visible_mask_gt(dist_test: np.ndarray, dist_gt: np.ndarray, delta_mm: float) -> np.ndarray:
    """Visible surface ``(H, W) bool`` of the model in the ground-truth pose.

    ``dist_test`` is the scene's distance image, ``dist_gt`` the model rendered in
    the ground-truth pose, both [mm]; ``delta_mm`` the visibility tolerance [mm].
    """
    return _visible(dist_test, dist_gt, delta_mm)


def visible_mask_est(
    dist_test: np.ndarray, dist_est: np.ndarray, visible_gt: np.ndarray, delta_mm: float
) -> np.ndarray:
    """Visible surface ``(H, W) bool`` of the model in the estimated pose.

    Besides the plain test, every pixel where the estimate is rendered and the
    ground truth is visible counts as visible: an estimate may occlude the scene
    where the true object is (Hodan et al., ECCVW 2016, eq. 14).
    """
    return _visible(dist_test, dist_est, delta_mm) | (visible_gt & (dist_est > 0))
