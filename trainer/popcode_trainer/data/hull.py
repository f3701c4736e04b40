"""A few points on an object's convex hull: what the runtime places to fit a box (``hull_points_mm``); and
:func:`with_hull_points`, which gives a model's objects these and the surface points that depth needs.

The runtime finds the translation whose projected points fill the detected box
(:mod:`popcode_runtime.geometry.translation`); it has no mesh, only what the model's
metadata carries. A box edge is set by the hull's support function ``h(d) =
max_p d·p`` in the direction of the edge, so the points are chosen for it:
greedily, each new point is the hull vertex extreme in the direction where the
chosen set falls furthest short of the whole hull (over ``_DIRECTIONS`` directions).

On the built-in parts :data:`HULL_POINTS` such points keep every box edge far
closer to the mesh's than the 8 corners of the 3-D box do, and, unlike
farthest-point sampling of the hull vertices, also on a slightly noisy copy of a
mesh, as a scan would be: bench/results/hull-points.md.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.population_code import fibonacci_lattice

from .bop import model_path
from .meshes import load_mesh
from .surface_sample import outer_surface_points
from .symmetry_check import check_object_symmetries

HULL_POINTS = 64  # about 1.5 kB of metadata per object
HULL_DECIMALS = 2  # 0.01 mm: far below a pixel, keeps the metadata short
_DIRECTIONS = 2000  # about 4.5 degrees apart


def hull_vertices_mm(vertices_mm: np.ndarray) -> np.ndarray:
    """Vertices ``(V, 3)`` of the convex hull of a point set; the points themselves if it has no volume."""
    points = np.asarray(vertices_mm, dtype=np.float64)
    try:
        return np.asarray(trimesh.convex.convex_hull(points).vertices)
    except Exception:  # qhull refuses flat or tiny point sets; their points are already few
        return points


def hull_points_mm(vertices_mm: np.ndarray, count: int = HULL_POINTS) -> np.ndarray:
    """At most ``count`` hull vertices ``(P, 3)`` [mm] that keep the silhouette, rounded to 0.01 mm.

    Fewer when they already reproduce the hull's support function in every
    sampled direction (a box needs its 8 corners only).
    """
    if count < 4:
        raise PopcodeError(f"need at least 4 hull points, got {count}")
    hull = hull_vertices_mm(vertices_mm)
    support = fibonacci_lattice(_DIRECTIONS) @ hull.T  # (D, V)
    full = support.max(axis=1)
    reached = np.full(len(full), -np.inf)
    tolerance = 1e-9 * max(float(np.ptp(hull, axis=0).max()), 1.0)
    chosen: list[int] = []
    while len(chosen) < count:
        shortfall = full - reached
        direction = int(np.argmax(shortfall))
        if shortfall[direction] <= tolerance:
            break
        vertex = int(np.argmax(support[direction]))
        chosen.append(vertex)
        reached = np.maximum(reached, support[:, vertex])
    return np.round(hull[chosen], HULL_DECIMALS)


def with_hull_points(objects: Mapping[int, Mapping[str, Any]], models_dir: str | Path | None,
                     count: int = HULL_POINTS) -> dict[int, dict[str, Any]]:
    """Copies of the ``models_info`` entries with the points the runtime places, from each mesh in ``models_dir``:
    ``hull_points_mm`` (to fit a box) and ``surface_points_mm`` with ``surface_normals`` (to read depth,
    :func:`~popcode_trainer.data.surface_sample.outer_surface_points`).

    Entries that already carry points keep them. Without a mesh the entry is
    left as it is, with a warning: the runtime then uses the 3-D box corners,
    which overestimate the silhouette and place the object too far away, and
    cannot use depth for it.
    """
    result = {int(obj_id): dict(info) for obj_id, info in objects.items()}
    missing: dict[str, list[int]] = {"hull_points_mm": [], "surface_points_mm": []}
    for obj_id, info in result.items():
        lacking = [key for key in missing if key not in info]
        if not lacking:
            continue
        try:
            mesh = load_mesh(model_path(models_dir, obj_id)) if models_dir else None
        except PopcodeError:
            mesh = None
        if mesh is None:
            missing[lacking[0]].append(obj_id)
            continue
        check_object_symmetries(model_path(models_dir, obj_id), info, obj_id, mesh)
        if "hull_points_mm" in lacking:
            info["hull_points_mm"] = hull_points_mm(np.asarray(mesh.vertices), count).tolist()
        if "surface_points_mm" in lacking:
            points, normals = outer_surface_points(mesh)
            info["surface_points_mm"], info["surface_normals"] = points.tolist(), normals.tolist()
    where = f"in {models_dir}" if models_dir else "(no models folder given)"
    if missing["hull_points_mm"]:
        warnings.warn(f"no mesh {where} for objects {missing['hull_points_mm']}: their metadata has no "
                      "hull_points_mm, so translation from the box uses the 3-D box corners and places them too far "
                      "away, and depth cannot place them", stacklevel=2)
    if missing["surface_points_mm"]:
        warnings.warn(f"no mesh {where} for objects {missing['surface_points_mm']}: their metadata has no "
                      "surface_points_mm, so depth cannot place them", stacklevel=2)
    return result
