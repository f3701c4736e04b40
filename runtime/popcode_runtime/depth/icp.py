"""Refinement of rotation and translation against the observed points, with small_gicp (the optional extra).

``pip install ./runtime[depth]`` adds `small_gicp <https://github.com/koide3/small_gicp>`_,
a maintained C++ registration library with numpy bindings; the default runtime
does not need it. Its generalized ICP (GICP: plane-to-plane through each
point's local covariance) aligns the object's camera-facing surface points,
in the starting pose, to the box's depth readings near it. GICP was chosen
by measurement over point-to-point and point-to-plane ICP, and the visible
model points as the moving cloud over the observed ones: the back of the
object has no readings to match, so it must not be in the fit
(bench/depth.py).

The result must stay an estimate of the same object: a pose whose centre
(the mean of its surface points) leaves the box or moves more than half the
diameter from the start's is refused, and so is one that fits the depth worse
(:func:`.placement.pose_with_depth`).
A continuous symmetry leaves the rotation about its axis unobservable; ICP
would drift along it freely, so only the axis's new direction is kept and the
rotation about it stays the start's (the pose moved along the symmetry
accordingly), as the axis-only code decodes it. Discrete symmetries need
nothing: ICP converges to the equivalent pose nearest its start.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping, Sequence
from types import ModuleType
from typing import Any

import numpy as np

from ..base.errors import PopcodeError, library_step
from ..geometry.camera import project_camera_points
from ..geometry.crop import box_edges
from ..geometry.rotations import rotation_between
from ..geometry.symmetries import continuous_symmetries
from .surface_fit import ObjectSurface, box_points, facing_camera

INSTALL_HINT = "pip install ./runtime[depth]"
OBSERVED_RADIUS = 0.6  # of the diameter: readings this far from the start's centre may belong to the object
DOWNSAMPLING = 0.05  # of the diameter: voxel size for the observed points (the surface points are sparser)
PIXELS_PER_VOXEL = 3  # readings kept along a voxel's side, each way
CORRESPONDENCE = 0.1  # of the diameter: the furthest pair GICP matches
NEIGHBOURS = 10  # points per local covariance
ITERATIONS = 30
MAX_MOVE = 0.5  # of the diameter: a refined centre further from the start's is another object
MIN_POINTS = 10  # observed or visible surface points, fewer is no fit


def require_small_gicp() -> ModuleType:
    """The small_gicp module, or one line saying how to install it."""
    try:
        return importlib.import_module("small_gicp")
    except ImportError as error:
        raise PopcodeError(f"refining the pose with depth needs small_gicp: {INSTALL_HINT}") from error


def refine_pose(R_m2c: np.ndarray, t_m2c_mm: np.ndarray, K: np.ndarray, depth_mm: np.ndarray, box: Sequence[float],
                surface: ObjectSurface, info: Mapping[str, Any]) -> tuple[tuple[np.ndarray, np.ndarray] | None,
                                                                         str | None]:
    """The pose refined by GICP from ``(R_m2c, t_m2c_mm)``, or None and why it cannot be (see the module docstring).

    ``info`` is the object's metadata entry, for its continuous symmetry.
    """
    gicp = require_small_gicp()
    diameter = surface.diameter_mm
    centre_m = surface.points_mm.mean(axis=0)
    centre_c = R_m2c @ centre_m + t_m2c_mm
    # a few readings per voxel of the downsampling are enough: skip pixels where they are much smaller
    pixel_mm = centre_c[2] / max(K[0, 0], K[1, 1])
    step = max(1, int(DOWNSAMPLING * diameter / (PIXELS_PER_VOXEL * pixel_mm)))
    observed = box_points(depth_mm, K, box, centre_c, OBSERVED_RADIUS * diameter, step)
    visible = surface.points_mm[facing_camera(surface, R_m2c, t_m2c_mm)]
    if len(observed) < MIN_POINTS or len(visible) < MIN_POINTS:
        return None, "too few depth readings near the object to refine its pose; kept the depth translation"
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = R_m2c, t_m2c_mm
    with library_step("refine the pose with small_gicp"):
        target, tree = gicp.preprocess_points(observed, downsampling_resolution=DOWNSAMPLING * diameter,
                                              num_neighbors=NEIGHBOURS, num_threads=1)
        source = gicp.PointCloud(visible)
        gicp.estimate_covariances(source, num_neighbors=NEIGHBOURS, num_threads=1)
        result = gicp.align(target, source, tree, start, registration_type="GICP",
                            max_correspondence_distance=CORRESPONDENCE * diameter, num_threads=1,
                            max_iterations=ITERATIONS)
    pose = np.asarray(result.T_target_source, dtype=np.float64)
    R, t = keep_symmetry_roll(R_m2c, pose[:3, :3], pose[:3, 3], info)
    if not np.isfinite(R).all() or not np.isfinite(t).all() or t[2] <= 0:
        return None, "refinement diverged; kept the depth translation"
    moved_c = R @ centre_m + t
    if np.linalg.norm(moved_c - centre_c) > MAX_MOVE * diameter or not _inside_box(moved_c, K, box):
        return None, "refinement moved the object out of its box; kept the depth translation"
    return (R, t), None


def keep_symmetry_roll(R_start: np.ndarray, R_m2c: np.ndarray, t_m2c_mm: np.ndarray,
                       info: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """``(R_m2c, t_m2c_mm)`` with the rotation about the object's continuous symmetry axis set back to
    ``R_start``'s, moved along the symmetry so that it is the same pose; unchanged without such a symmetry.

    The symmetry ``x -> S x + o - S o`` (axis through offset ``o``) maps the
    pose ``(R, t)`` to the equivalent ``(R S, t + R (o - S o))``; ``S`` is the
    rotation about the axis that makes ``R S`` map the axis where ``R`` does
    with the least rotation from ``R_start``.
    """
    continuous = continuous_symmetries(info)
    if not continuous:
        return R_m2c, t_m2c_mm
    axis, offset = continuous[0]
    R_kept = rotation_between(R_start @ axis, R_m2c @ axis) @ R_start
    S = R_m2c.T @ R_kept  # a rotation about the axis: both map it to the same direction
    return R_kept, t_m2c_mm + R_m2c @ (offset - S @ offset)


def _inside_box(point_c_mm: np.ndarray, K: np.ndarray, box: Sequence[float]) -> bool:
    """True if a camera-frame point projects inside the box's silhouette edges."""
    u, v = project_camera_points(point_c_mm[None], K)[0]
    x_min, y_min, x_max, y_max = box_edges(box)
    return bool(x_min <= u <= x_max and y_min <= v <= y_max)
