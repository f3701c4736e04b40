"""The exact distance of points from a mesh's surface, for the tests that check a symmetry maps a mesh onto itself.

``trimesh.proximity.closest_point_naive`` measures every point against every triangle (seconds for a few thousand
triangles and a few hundred points); ``trimesh.proximity.closest_point`` needs rtree. Here only the triangles that
can be nearer than the nearest vertex are measured: a point lies at least ``|p - c| - r`` from a triangle of centroid
``c`` and circumradius about it ``r``, and a vertex is on the surface, so the nearest triangle is always among them.
tests/data/test_mesh_distance.py compares the two.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree


def surface_distance_mm(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """(n,) distance of each of the (n, 3) points from the nearest point of the mesh's triangles, in the mesh's
    units; the same values as ``closest_point_naive``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    triangles = np.asarray(mesh.triangles, dtype=np.float64)
    centroids = triangles.mean(axis=1)
    radii = np.linalg.norm(triangles - centroids[:, None], axis=2).max(axis=1)
    nearest_vertex, _ = cKDTree(np.asarray(mesh.vertices, dtype=np.float64)).query(points)
    reach = nearest_vertex + radii.max() + 1e-9
    candidates = cKDTree(centroids).query_ball_point(points, reach)
    point_ids = np.repeat(np.arange(len(points)), [len(found) for found in candidates])
    triangle_ids = np.concatenate([np.asarray(found, dtype=np.intp) for found in candidates])
    close = np.linalg.norm(points[point_ids] - centroids[triangle_ids], axis=1) <= nearest_vertex[point_ids] \
        + radii[triangle_ids] + 1e-9
    point_ids, triangle_ids = point_ids[close], triangle_ids[close]
    on_triangle = trimesh.triangles.closest_point(triangles[triangle_ids], points[point_ids])
    distance = np.full(len(points), np.inf)
    np.minimum.at(distance, point_ids, np.linalg.norm(on_triangle - points[point_ids], axis=1))
    return distance
