"""Surface samples of a mesh: how far a rigid motion carries them off the surface (what the symmetry checks
measure with), and the few outer-surface points the runtime's depth step places (``surface_points_mm``).

The distance of a moved sample to the surface is measured to a denser sample of the same surface (a k-d
tree), an upper bound of the true distance that exceeds it by about half the sample spacing (its target:
``_SPACING`` of the diameter).

The depth step compares the object's camera-facing points with a depth image, so its points must lie on
the surface a camera can see. A mesh built of overlapping closed parts (the built-in parts, many CAD
exports) also has faces inside the solid; a sample whose point, moved a hair along its normal, lies inside
another part of the mesh (generalised winding number above one half) is such a face and is dropped.
Farthest-point sampling then spreads :data:`SURFACE_POINTS` of the rest evenly over the surface.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.depth.surface_fit import MAX_SURFACE_POINTS, MIN_SURFACE_POINTS

PERCENTILE = 99.0  # of the moved samples; tolerates a stray sliver, not a misplaced feature
_QUERY_POINTS = 1000
_SPACING = 0.004  # of the diameter: target spacing of the reference sample
_REFERENCE_POINTS = (20_000, 200_000)
_SEED = 0
SURFACE_POINTS = MAX_SURFACE_POINTS  # 512: 3-5 mm apart on a 60 mm part
_SURFACE_CANDIDATES = 2048  # samples tested for being on the outer surface before the even spread is chosen
_NORMAL_STEP = 1e-3  # of the largest extent: how far a sample moves along its normal for the inside test
_DECIMALS = 2, 3  # points to 0.01 mm, normals to 0.001: far below the depth step's tolerance, short metadata


@dataclass(frozen=True)
class SurfaceSample:
    """Sparse query points and a dense reference sample of one mesh's surface [mm]."""

    points_mm: np.ndarray  # (P, 3)
    reference: cKDTree
    diameter_mm: float
    centroid_mm: np.ndarray  # (3,) the surface's area-weighted centre: exact, where the samples' mean is noisy


def diameter_mm(mesh: trimesh.Trimesh, info: Mapping[str, Any]) -> float:
    """The declared diameter when it is a positive number, else the bounding-box diagonal."""
    declared = info.get("diameter")
    if isinstance(declared, (int, float)) and np.isfinite(declared) and declared > 0:
        return float(declared)
    return float(np.linalg.norm(mesh.extents))


def surface_sample(mesh: trimesh.Trimesh, diameter_mm: float, name: str) -> SurfaceSample:
    """Seeded surface samples of ``mesh``: the reference dense enough to resolve 2 % of the diameter."""
    area = float(mesh.area)
    if not np.isfinite(area) or area <= 0:
        raise PopcodeError(f"{name}: the mesh has no surface area; its symmetries cannot be checked")
    low, high = _REFERENCE_POINTS
    count = int(np.clip(area / (_SPACING * diameter_mm) ** 2, low, high))
    reference, _ = trimesh.sample.sample_surface(mesh, count, seed=_SEED)
    points, _ = trimesh.sample.sample_surface(mesh, _QUERY_POINTS, seed=_SEED + 1)
    centroid = (mesh.triangles_center * mesh.area_faces[:, None]).sum(axis=0) / area
    return SurfaceSample(np.asarray(points), cKDTree(np.concatenate([reference, mesh.vertices])), diameter_mm,
                         centroid)


def surface_distance(sample: SurfaceSample, R: np.ndarray, t_mm: np.ndarray, percentile: float = PERCENTILE,
                     within: float | None = None) -> float:
    """How far the moved samples lie from the surface: the ``percentile`` distance, as a share of the diameter.

    ``within`` (a share of the diameter), for a caller that needs the distance only where it is at most that: the
    same distance there, ``inf`` for some motions beyond it. The k-d tree then gives up on a sample once it is
    that far (a motion that does not fit: ten times faster), and only the few far samples of one that nearly
    fits are looked up in full."""
    moved = sample.points_mm @ np.asarray(R).T + t_mm
    if within is None:
        distance, _ = sample.reference.query(moved)
    else:
        # the tree reports only neighbours closer than its bound: a hair above `within`, so none at it is lost
        distance, _ = sample.reference.query(moved, distance_upper_bound=within * sample.diameter_mm * (1 + 1e-9))
        far = np.isinf(distance)
        # numpy's percentile interpolates between the order statistics at floor(q (n - 1)) and the next; when
        # the first lies beyond `within`, so does the percentile
        if np.count_nonzero(~far) <= int(np.floor(percentile / 100.0 * (len(distance) - 1))):
            return np.inf
        distance[far], _ = sample.reference.query(moved[far])
    return float(np.percentile(distance, percentile)) / sample.diameter_mm


def _winding_numbers(triangles: np.ndarray, points: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Generalised winding number ``(N,)`` of each point about a closed surface ``(T, 3, 3)``: 1 inside, 0 outside.

    The solid angle of every triangle seen from the point (Van Oosterom and Strackee) over 4 pi.
    """
    result = np.empty(len(points))
    for start in range(0, len(points), chunk):
        a, b, c = (triangles[None, :, k] - points[start : start + chunk, None] for k in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        numerator = np.einsum("ptk,ptk->pt", a, np.cross(b, c))
        denominator = (la * lb * lc + np.einsum("ptk,ptk->pt", a, b) * lc + np.einsum("ptk,ptk->pt", a, c) * lb
                       + np.einsum("ptk,ptk->pt", b, c) * la)
        result[start : start + chunk] = np.arctan2(numerator, denominator).sum(axis=1) / (2.0 * np.pi)
    return result


def _inside_other_parts(mesh: trimesh.Trimesh, points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which points ``(N,)`` lie inside a connected part of the mesh other than the one their face ``faces`` is on
    (only points within a part's bounding box are tested against it)."""
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    inside = np.zeros(len(points), dtype=bool)
    for part in np.unique(labels):
        triangles = np.asarray(mesh.triangles[labels == part], dtype=np.float64)
        low, high = triangles.min(axis=(0, 1)), triangles.max(axis=(0, 1))
        tested = (labels[faces] != part) & np.all((points >= low) & (points <= high), axis=1)
        if tested.any():
            inside[tested] |= np.abs(_winding_numbers(triangles, points[tested])) > 0.5
    return inside


def _farthest_points(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` points chosen greedily, each the farthest from those chosen before (the first: 0)."""
    chosen = [0]
    distance = np.linalg.norm(points - points[0], axis=1)
    while len(chosen) < min(count, len(points)):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def outer_surface_points(mesh: trimesh.Trimesh, count: int = SURFACE_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """At most ``count`` points ``(P, 3)`` [mm] spread evenly over the mesh's outer surface and their outward unit
    normals ``(P, 3)``, rounded for the metadata; seeded, so one mesh always gives the same points."""
    points, faces = trimesh.sample.sample_surface(mesh, _SURFACE_CANDIDATES, seed=_SEED)
    points, normals = np.asarray(points), np.asarray(mesh.face_normals[faces])
    step = _NORMAL_STEP * float(np.ptp(mesh.vertices, axis=0).max())
    outer = ~_inside_other_parts(mesh, points + step * normals, np.asarray(faces))
    points, normals = points[outer], normals[outer]
    if len(points) < MIN_SURFACE_POINTS:
        raise PopcodeError(f"only {len(points)} of {_SURFACE_CANDIDATES} surface samples lie on the mesh's outer "
                           "surface; is it closed and facing outwards?")
    chosen = _farthest_points(points, count)
    normals = normals[chosen] / np.linalg.norm(normals[chosen], axis=1, keepdims=True)
    return np.round(points[chosen], _DECIMALS[0]), np.round(normals, _DECIMALS[1])
