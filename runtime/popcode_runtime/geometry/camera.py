"""The pinhole camera, in OpenCV's convention: ``K`` 3x3, x right, y down, z forward, pixel centres at integers.

One definition of the camera matrix's parsing and of point projection for the
runtime (box fitting), the renderer and the BOP metrics (MSPD).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..base.checks import number_array
from ..base.errors import PopcodeError

MAX_FOCAL_PX = 1e6  # a 1000 mm lens on 1 um pixels; beyond this the numbers are not a camera
MAX_PRINCIPAL_PX = 1e6
# A depth camera's unit (BOP's depth_scale: mm = value x depth_scale), kept with the camera it belongs to:
# 0.1 um (a float depth in nm) to 10 m.
MIN_DEPTH_SCALE, MAX_DEPTH_SCALE = 1e-4, 1e4
# What a camera's frame sees across its width or height. Superzooms reach about 0.7 deg (3000 mm equivalent) and
# the widest rectilinear lenses about 125 deg; a pinhole image cannot reach 180 (a fisheye's must be undistorted
# first). Outside these bounds K is another image's, or its numbers are not in this image's pixels.
MIN_FIELD_OF_VIEW_DEG, MAX_FIELD_OF_VIEW_DEG = 0.5, 170.0


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


def camera_for_image(K: np.ndarray, image_shape: tuple[int, ...],
                     crop_origin: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """``K`` (as :func:`parse_camera_matrix` returns it) checked against the image it comes with, in that image's
    pixels; refused in one line where the two cannot belong together (docs/design.md#conventions).

    Without ``crop_origin`` the image is the whole frame K belongs to: the principal point lies on it (within
    ``[0, W] x [0, H]``, either pixel convention) and the field of view across its width and its height within
    [:data:`MIN_FIELD_OF_VIEW_DEG`, :data:`MAX_FIELD_OF_VIEW_DEG`]. With ``crop_origin`` ``(x, y)``, the image's
    top-left in K's frame, the image is a crop of that frame (it may see as little as it likes): K's principal
    point must lie in its frame, the crop must overlap the frame and lie within half the widest field of view of
    the optical axis; the principal point is then moved into the crop's pixels.
    """
    height, width = image_shape[:2]
    if crop_origin is None:
        _check_whole_frame(K, width, height)
        return K
    shifted = K.copy()
    shifted[:2, 2] -= _checked_crop_origin(K, crop_origin, width, height)
    return shifted


def _check_whole_frame(K: np.ndarray, width: int, height: int) -> None:
    """Refuse a principal point off the image (K is another image size's, or the image a crop) and a field of view
    no camera has (fx, fy in another image's pixels)."""
    cx, cy = K[0, 2], K[1, 2]
    if not (0.0 <= cx <= width and 0.0 <= cy <= height):
        raise PopcodeError(f"the camera K puts its principal point at ({cx:g}, {cy:g}), outside the {width}x{height} "
                           "image: K is another image size's, or the image a crop of K's frame (then give the "
                           "crop's top-left in that frame as the crop origin)")
    spans = [math.degrees(math.atan(centre / focal) + math.atan((size - centre) / focal))
             for focal, centre, size in ((K[0, 0], cx, width), (K[1, 1], cy, height))]
    if min(spans) < MIN_FIELD_OF_VIEW_DEG or max(spans) > MAX_FIELD_OF_VIEW_DEG:
        raise PopcodeError(f"the camera K (fx {K[0, 0]:g}, fy {K[1, 1]:g}) sees {spans[0]:.3g} x {spans[1]:.3g} deg "
                           f"across the {width}x{height} image; a camera sees {MIN_FIELD_OF_VIEW_DEG:g} to "
                           f"{MAX_FIELD_OF_VIEW_DEG:g} deg: are fx and fy in this image's pixels?")


def _checked_crop_origin(K: np.ndarray, crop_origin: Sequence[float] | np.ndarray, width: int,
                         height: int) -> np.ndarray:
    """The crop's top-left ``(2,)`` in K's frame, refused where the crop cannot be part of that frame."""
    origin = number_array(crop_origin, "the crop origin (x, y)", (2,))
    if np.abs(origin).max() > MAX_PRINCIPAL_PX:
        raise PopcodeError(f"the crop origin {origin.tolist()} lies beyond {MAX_PRINCIPAL_PX:g} px of K's frame")
    if min(K[0, 2], K[1, 2]) < 0.0:
        raise PopcodeError(f"the camera K puts its principal point at ({K[0, 2]:g}, {K[1, 2]:g}), outside its own "
                           "frame: with a crop origin, K is the whole frame's camera, not the crop's")
    if origin[0] + width <= 0.0 or origin[1] + height <= 0.0:
        raise PopcodeError(f"the crop origin {origin.tolist()} puts the {width}x{height} image wholly left of or "
                           "above K's frame: it is the crop's top-left pixel in that frame")
    # skew (0 in every BOP camera) is left out of the angles
    farthest = max(math.degrees(math.atan(max(abs(low - centre), abs(low + size - centre)) / focal))
                   for focal, centre, low, size in ((K[0, 0], K[0, 2], origin[0], width),
                                                    (K[1, 1], K[1, 2], origin[1], height)))
    if farthest > MAX_FIELD_OF_VIEW_DEG / 2:
        raise PopcodeError(f"the crop origin {origin.tolist()} puts the {width}x{height} image {farthest:.3g} deg off "
                           f"the optical axis of K (fx {K[0, 0]:g}, fy {K[1, 1]:g}), beyond half the widest field "
                           f"of view ({MAX_FIELD_OF_VIEW_DEG:g} deg): is the origin in K's frame's pixels?")
    return origin


def project_camera_points(points_c_mm: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``(..., 2)`` [px] of camera-frame points ``(..., 3)`` [mm] (in front of the camera)."""
    uvw = np.asarray(points_c_mm) @ np.asarray(K).T
    return uvw[..., :2] / uvw[..., 2:3]


def project_points(points_m_mm: np.ndarray, K: np.ndarray, R_m2c: np.ndarray, t_m2c_mm: np.ndarray) -> np.ndarray:
    """Pixel coordinates ``(N, 2)`` [px] of model points ``(N, 3)`` [mm] seen in the pose ``x_c = R x_m + t``."""
    return project_camera_points(np.asarray(points_m_mm) @ np.asarray(R_m2c).T + np.asarray(t_m2c_mm), K)
