"""Hull points for the runtime's translation: few, on the hull, and the projected box of the whole mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from popcode_runtime.geometry.camera import project_points
from popcode_runtime.geometry.rotations import random_rotations
from popcode_trainer.data.hull import HULL_POINTS, hull_points_mm, hull_vertices_mm, with_hull_points
from popcode_trainer.data.objects import build_part, write_builtin_models
from popcode_trainer.data.render import camera_matrix

BOX_TOLERANCE = 0.010  # of the box size: what bench/results/hull-points.md measured on the built-in parts


def _box(uv: np.ndarray) -> np.ndarray:
    return np.concatenate([uv.min(axis=0), uv.max(axis=0)])


def test_a_box_needs_only_its_eight_corners() -> None:
    mesh = trimesh.creation.box(extents=(40.0, 20.0, 10.0))
    points = hull_points_mm(np.asarray(mesh.vertices))
    expected = {(x, y, z) for x in (-20.0, 20.0) for y in (-10.0, 10.0) for z in (-5.0, 5.0)}
    assert {tuple(p) for p in points.tolist()} == expected


@pytest.mark.parametrize("obj_id", [1, 2, 5])  # the parts with curved rims, where points must be chosen
def test_hull_points_keep_the_projected_box(obj_id: int) -> None:
    vertices = np.asarray(build_part(obj_id).vertices)
    points = hull_points_mm(vertices)
    assert len(points) == HULL_POINTS
    assert np.array_equal(points, np.round(points, 2))
    hull = hull_vertices_mm(vertices)
    assert np.abs(points[:, None] - hull[None]).max(axis=2).min(axis=1).max() <= 0.005 + 1e-9  # hull vertices
    K = camera_matrix(256, 256)
    rng = np.random.default_rng(obj_id)
    diameter = np.ptp(vertices, axis=0).max()
    worst = 0.0
    for R in random_rotations(200, rng):
        t = 2.5 * diameter * np.linalg.solve(K, np.append(rng.uniform(20, 236, size=2), 1.0))
        full, fit = _box(project_points(vertices, K, R, t)), _box(project_points(points, K, R, t))
        worst = max(worst, np.abs(fit - full).max() / np.ptp(full.reshape(2, 2), axis=0).max())
    assert worst < BOX_TOLERANCE


def test_entries_get_hull_points_or_keep_their_box_with_a_warning(tmp_path: Path) -> None:
    models_dir = write_builtin_models(tmp_path / "models")
    objects = {3: {"diameter": 80.0}, 6: {"diameter": 70.0, "hull_points_mm": [[0.0, 0.0, 0.0]] * 4},
               99: {"diameter": 10.0}}
    with pytest.warns(UserWarning, match=r"objects \[99\]: their metadata has no hull_points_mm"):
        result = with_hull_points(objects, models_dir)
    assert len(result[3]["hull_points_mm"]) <= HULL_POINTS and result[3]["diameter"] == 80.0
    assert result[6]["hull_points_mm"] == [[0.0, 0.0, 0.0]] * 4  # kept as given
    assert "hull_points_mm" not in result[99] and "hull_points_mm" not in objects[3]  # the input is not changed
    with pytest.warns(UserWarning, match="no models folder given"):
        assert "hull_points_mm" not in with_hull_points({3: {}}, "")[3]
