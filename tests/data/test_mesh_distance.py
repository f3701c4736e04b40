"""tests/mesh_distance.py, the pruned exact distance from a mesh's surface, against trimesh's measure of every point
against every triangle: the same values for points on the surface, near it, inside and far away."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from mesh_distance import surface_distance_mm

from popcode_runtime.geometry.rotations import random_rotations
from popcode_trainer.data.objects import build_part


@pytest.mark.parametrize("obj_id", [1, 6])  # long thin facets of a revolved part; boxes and cylinders
def test_the_same_distances_as_every_triangle(obj_id: int) -> None:
    mesh = build_part(obj_id)
    rng = np.random.default_rng(obj_id)
    points, _ = trimesh.sample.sample_surface(mesh, 64, seed=obj_id)
    turned = points @ random_rotations(1, rng)[0].T
    queries = np.concatenate([points, turned, 0.5 * turned, points + rng.normal(0.0, 1.0, points.shape),
                              rng.normal(0.0, 300.0, (32, 3)), mesh.vertices[:8]])
    _, every_triangle, _ = trimesh.proximity.closest_point_naive(mesh, queries)
    np.testing.assert_array_equal(surface_distance_mm(mesh, queries), every_triangle)
    assert every_triangle[-8:].max() == 0.0 and every_triangle[len(points):].max() > 1.0  # on it and off it
