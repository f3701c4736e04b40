"""Translation from a depth image: the distance the box can only guess, read off the object's own surface.

The box fixes the ray to the object well but its distance poorly (a rotation
error changes the silhouette's size, and the distance with it). A registered
depth image measures that distance. With the estimated rotation, the object's
surface points that face the camera (``surface_points_mm`` and
``surface_normals`` in the model metadata) are placed on the box's ray and
projected into the depth image; at each point's pixel the reading minus the
point's depth is its residual. A 1-D search along the ray picks the offset
whose surface the readings confirm most (residuals near zero) while seeing
through it least (readings far behind it): an occluder in front confirms a
surface the readings then see through elsewhere, the bin floor is seen only
off the object's silhouette, holes have no reading and count for nothing.
Averaging the confirming residuals, re-projected a few times, refines the
distance. The search tolerates a tenth of the diameter, so that a rotation
some degrees off (whose surface cannot match the readings closely) is still
placed; the average then narrows to the residuals' own spread. The count of
confirmed points less those seen through, as a share of the visible points,
is each pose's ``depth_fit``: how much of the object the depth confirms.
On rendered bin scenes with the true rotation the translation comes within
about 0.3 mm (median) of the truth; bench/depth.py measures it.

Conventions: depth is the z coordinate [mm] of each pixel's surface point
(BOP's ``depth_scale``: mm = value x depth_scale), 0 where the sensor has no
reading; OpenCV camera, model-to-camera poses, as everywhere in popcode.
Refinement of rotation and translation (ICP) is :mod:`.icp`; one
instance's whole placement (box, depth, refinement, best start) is :mod:`.placement`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..base.checks import number
from ..base.errors import PopcodeError
from ..base.text_enum import TextEnum
from ..geometry.camera import MAX_DEPTH_SCALE, MIN_DEPTH_SCALE, project_camera_points
from ..geometry.crop import MAX_IMAGE_PIXELS, read_image_file

MIN_SURFACE_POINTS, MAX_SURFACE_POINTS = 16, 512  # per object in the metadata: at most about 25 kB of JSON
MAX_DEPTH_MM = 1e5  # 100 m: no depth camera reads further; a reading beyond means a wrong depth_scale
TOLERANCE_OF_DIAMETER = 0.03  # a reading confirms a point within this share of the object's diameter ...
TOLERANCE_OF_DISTANCE = 0.003  # ... or of its distance, whichever is larger (sensor noise grows with distance)
MIN_TOLERANCE_MM = 1.0
COARSE_OF_DIAMETER = 0.1  # the tolerance while searching: a rotation some degrees off still matches this well
SPREAD_WINDOW = 3.7  # the final average keeps residuals within this many median absolute deviations (2.5 sigma)
SEARCH_OF_DISTANCE = 0.1  # the offset along the ray is searched within +-max(diameter, this share of the distance)
MIN_CONFIRMED_POINTS = 8  # fewer confirmed surface points than this is no measurement
MIN_CONFIRMED_SHARE = 0.05  # of the visible points: a rotation some degrees off confirms little more
REFINEMENTS = 4  # re-projections after the search


class TranslationSource(TextEnum):
    """Where a prediction's translation came from."""

    BOX = "box"  # fitted to the detected box (no depth given, or the depth was unusable for this instance)
    DEPTH = "depth"  # the box's ray at the distance the depth image measures
    REFINED = "refined"  # rotation and translation refined against the observed points (ICP)


@dataclass(frozen=True)
class ObjectSurface:
    """Points on an object's outer surface and their outward unit normals, model frame [mm]."""

    points_mm: np.ndarray  # (P, 3)
    normals: np.ndarray  # (P, 3)
    diameter_mm: float  # the largest distance between two of the points


def object_surface(info: Mapping[str, Any]) -> ObjectSurface | None:
    """The surface points of a ``models_info``-style entry; None when it has none (a model exported before them)."""
    if "surface_points_mm" not in info and "surface_normals" not in info:
        return None
    try:
        points = np.asarray(info.get("surface_points_mm"), dtype=np.float64)
        normals = np.asarray(info.get("surface_normals"), dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        points = normals = np.empty(0)
    count = f"{MIN_SURFACE_POINTS} to {MAX_SURFACE_POINTS}"
    if points.ndim != 2 or points.shape[1:] != (3,) or not MIN_SURFACE_POINTS <= len(points) <= MAX_SURFACE_POINTS \
            or not np.isfinite(points).all():
        raise PopcodeError(f"surface_points_mm must be a list of {count} finite points [x, y, z]")
    if normals.shape != points.shape or not np.isfinite(normals).all():
        raise PopcodeError(f"surface_normals must be {len(points)} finite vectors [x, y, z], one per surface point")
    length = np.linalg.norm(normals, axis=1)
    if np.any(np.abs(length - 1.0) > 0.01):
        raise PopcodeError("surface_normals must be unit vectors")
    diameter = _largest_distance(points)
    if diameter <= 0.0:
        raise PopcodeError("surface_points_mm are all one point")
    return ObjectSurface(points, normals / length[:, None], diameter)


def _largest_distance(points: np.ndarray) -> float:
    """The largest distance between two of ``points`` (P, 3): from their Gram matrix, one product instead of a
    (P, P, 3) array of differences (every model load checks its surfaces: 1 ms, not 5, at 512 points); centred
    first, so that a cloud far from the origin loses no digits and one point repeated gives exactly 0."""
    centred = points - points.mean(axis=0)
    squared = np.einsum("ij,ij->i", centred, centred)
    return float(np.sqrt(max((squared[:, None] + squared[None] - 2.0 * centred @ centred.T).max(), 0.0)))


def read_depth(path: str | Path, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """A depth image file as stored (e.g. 16-bit PNG); one channel, else an error naming the file and its channels
    (read with alpha, which OpenCV's colour reading would drop)."""
    depth = read_image_file(path, max_pixels, "depth image", as_stored=True)
    if depth.ndim != 2:
        raise PopcodeError(f"depth image {path} has {depth.shape[2]} channels; a depth image has one")
    return depth


def check_depth(depth: Any, image_shape: tuple[int, ...], depth_scale: float) -> np.ndarray:
    """``depth`` ``(H, W)`` (integers or floats, 0: no reading) in mm as float32, checked against the image.

    Refuses, in one line each: not a 2-D array of numbers, 8-bit values, a size other than
    the image's, NaN or inf, negative values, a ``depth_scale`` (mm per unit)
    outside [1e-4, 1e4] and readings beyond 100 m (a wrong scale). All
    zeros is not an error: each instance then keeps the box's translation.
    """
    if not isinstance(depth, np.ndarray):
        raise PopcodeError(f"depth must be a numpy array, got {type(depth).__name__}")
    if depth.ndim != 2:
        raise PopcodeError(f"depth must be a 2-D array (H, W), got shape {depth.shape}")
    if not (np.issubdtype(depth.dtype, np.integer) or np.issubdtype(depth.dtype, np.floating)):
        raise PopcodeError(f"depth must hold integers or floats, got {depth.dtype}")
    if depth.dtype.itemsize == 1:
        raise PopcodeError("depth is 8-bit: 256 levels cannot measure a distance (a grey or colour picture?); a depth "
                           "image is 16-bit (as BOP stores it) or float")
    if depth.shape != tuple(image_shape[:2]):
        raise PopcodeError(f"depth is {depth.shape[1]}x{depth.shape[0]} but the image is {image_shape[1]}x"
                           f"{image_shape[0]}: they must be one registered camera frame")
    scale = number(depth_scale, "depth_scale", MIN_DEPTH_SCALE, MAX_DEPTH_SCALE)
    if depth.size == 0:
        return depth.astype(np.float32)
    if np.issubdtype(depth.dtype, np.floating) and not np.isfinite(depth).all():
        raise PopcodeError("depth contains NaN or inf; mark pixels without a reading with 0")
    low, high = depth.min(), depth.max()
    if low < 0:
        raise PopcodeError(f"depth contains negative values (down to {low:g}); 0 marks a pixel without a reading")
    if float(high) * scale > MAX_DEPTH_MM:
        raise PopcodeError(f"depth readings reach {float(high) * scale:.3g} mm ({high:g} x depth_scale {scale:g}), "
                           f"beyond {MAX_DEPTH_MM / 1000:g} m: is depth_scale the mm per depth unit?")
    return depth.astype(np.float32) * np.float32(scale)


def _pixel_bounds(box: Sequence[float], shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """The whole pixels ``x0, y0, x1, y1`` (exclusive ends) of a BOP box, clipped to the image."""
    x, y, w, h = (float(v) for v in box)
    return (max(int(np.floor(x)), 0), max(int(np.floor(y)), 0), min(int(np.ceil(x + w)) + 1, shape[1]),
            min(int(np.ceil(y + h)) + 1, shape[0]))


def has_readings(depth_mm: np.ndarray, box: Sequence[float]) -> bool:
    """True if any pixel of the box has a depth reading."""
    x0, y0, x1, y1 = _pixel_bounds(box, depth_mm.shape)
    return bool(np.any(depth_mm[y0:y1, x0:x1] > 0))


def box_points(depth_mm: np.ndarray, K: np.ndarray, box: Sequence[float], centre_mm: np.ndarray, radius_mm: float,
               step_px: int = 1) -> np.ndarray:
    """Camera-frame points ``(N, 3)`` [mm] of the box's readings (every ``step_px``-th pixel each way) that lie
    within ``radius_mm`` of ``centre_mm``."""
    x0, y0, x1, y1 = _pixel_bounds(box, depth_mm.shape)
    window = depth_mm[y0:y1:step_px, x0:x1:step_px]
    v, u = np.nonzero((window > centre_mm[2] - radius_mm) & (window < centre_mm[2] + radius_mm))
    z = window[v, u].astype(np.float64)
    u, v = x0 + step_px * u, y0 + step_px * v
    points = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
    points[:, 0] -= K[0, 1] * points[:, 1] / K[1, 1]  # skew, usually 0
    return points[np.linalg.norm(points - centre_mm, axis=1) < radius_mm]


def facing_camera(surface: ObjectSurface, R_m2c: np.ndarray, t_m2c_mm: np.ndarray) -> np.ndarray:
    """Which surface points ``(P,)`` bool face the camera in the pose (the side a depth camera can see)."""
    points = surface.points_mm @ R_m2c.T + t_m2c_mm
    return np.einsum("ij,ij->i", surface.normals @ R_m2c.T, points) < 0.0


def _residuals_mm(points_c_mm: np.ndarray, K: np.ndarray, depth_mm: np.ndarray) -> np.ndarray:
    """Reading minus depth [mm] at the pixel of each camera-frame point that falls on a reading."""
    points = points_c_mm[points_c_mm[:, 2] > 1e-6]
    uv = project_camera_points(points, K)
    height, width = depth_mm.shape
    inside = (uv[:, 0] > -0.5) & (uv[:, 0] < width - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < height - 0.5)
    pixels = np.rint(uv[inside]).astype(np.int64)
    readings = depth_mm[pixels[:, 1], pixels[:, 0]]
    valid = readings > 0
    return readings[valid] - points[inside][valid, 2]


def tolerance_mm(surface: ObjectSurface, distance_mm: float) -> float:
    """How far [mm] a reading may lie from a surface point and still confirm it."""
    return max(TOLERANCE_OF_DIAMETER * surface.diameter_mm, TOLERANCE_OF_DISTANCE * distance_mm, MIN_TOLERANCE_MM)


def depth_fit(R_m2c: np.ndarray, t_m2c_mm: np.ndarray, K: np.ndarray, depth_mm: np.ndarray,
              surface: ObjectSurface) -> float:
    """How well the depth confirms a pose, in [-1, 1]: the share of the visible surface points that the readings
    confirm, less the share they see through (1: every visible point confirmed; an occluded object scores its
    visible share)."""
    visible = facing_camera(surface, R_m2c, t_m2c_mm)
    residuals = _residuals_mm(surface.points_mm[visible] @ R_m2c.T + t_m2c_mm, K, depth_mm)
    tolerance = tolerance_mm(surface, float(t_m2c_mm[2]))
    confirmed = np.count_nonzero(np.abs(residuals) < tolerance) - np.count_nonzero(residuals > 3.0 * tolerance)
    return float(confirmed) / max(int(visible.sum()), 1)


def translation_from_depth(R_m2c: np.ndarray, t_box_mm: np.ndarray, K: np.ndarray, depth_mm: np.ndarray,
                           surface: ObjectSurface) -> tuple[np.ndarray | None, str | None]:
    """The translation ``(3,)`` [mm] on the ray of ``t_box_mm`` at the distance the depth measures, or None and
    why the depth cannot place this instance (see the module docstring).

    The search and the test of enough support use a coarse tolerance (a tenth
    of the diameter), so that a rotation some degrees off, whose surface
    cannot match the readings closely, is still placed; the final average
    narrows to the residuals' own spread, down to :func:`tolerance_mm` when
    the rotation is right.
    """
    distance = float(np.linalg.norm(t_box_mm))
    ray = np.asarray(t_box_mm, dtype=np.float64) / distance
    rotated, normals = surface.points_mm @ R_m2c.T, surface.normals @ R_m2c.T
    fine = tolerance_mm(surface, distance)
    coarse = max(COARSE_OF_DIAMETER * surface.diameter_mm, fine)

    def residuals(at_mm: float) -> tuple[np.ndarray, int]:
        points = rotated + at_mm * ray
        visible = np.einsum("ij,ij->i", normals, points) < 0.0
        return _residuals_mm(points[visible], K, depth_mm), int(visible.sum())

    found, visible = residuals(distance)
    if len(found) < MIN_CONFIRMED_POINTS:
        return None, "no depth readings where the object's surface should be (holes, or outside the image)"
    found = np.sort(found)
    search = max(surface.diameter_mm, SEARCH_OF_DISTANCE * distance)
    offsets = np.arange(-search, search + fine / 2.0, fine / 2.0)
    confirmed = np.searchsorted(found, offsets + coarse) - np.searchsorted(found, offsets - coarse)
    seen_through = len(found) - np.searchsorted(found, offsets + 3.0 * coarse)
    distance += float(offsets[np.argmax(confirmed - seen_through)]) / ray[2]
    window = coarse
    for step in range(REFINEMENTS):
        found, visible = residuals(distance)
        near = found[np.abs(found) < coarse]
        if len(near) < max(MIN_CONFIRMED_POINTS, MIN_CONFIRMED_SHARE * visible):
            return None, (f"too little of the object's surface in the depth near the box's distance: {len(near)} of "
                          f"its {visible} visible points (less than {100 * MIN_CONFIRMED_SHARE:.0f} %)")
        if step == 1:  # centred once: the spread left is the rotation's error and the sensor's noise
            window = float(np.clip(SPREAD_WINDOW * np.median(np.abs(near - np.median(near))), fine, coarse))
        close = found[np.abs(found) < window]
        distance += float((close if len(close) else near).mean()) / ray[2]
    return distance * ray, None
