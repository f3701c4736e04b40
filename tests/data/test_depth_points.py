"""The surface points a model carries for depth (issue 29), and the translation they give from rendered depth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from popcode_runtime.depth.surface_fit import (
    MAX_SURFACE_POINTS,
    check_depth,
    object_surface,
    read_depth,
    translation_from_depth,
)
from popcode_runtime.geometry.translation import object_points_mm, translation_from_box
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.hull import with_hull_points
from popcode_trainer.data.objects import build_part, write_builtin_models
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.data.surface_sample import outer_surface_points


def test_surface_points_lie_on_the_outer_surface_only():
    """The cross connector is a bar with bosses and stubs whose closed parts overlap: the faces inside the bar
    (the bosses' and stubs' inner ends) give no points."""
    points, normals = outer_surface_points(build_part(5))
    assert len(points) == MAX_SURFACE_POINTS
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=2e-3)
    inside_bar = np.all(np.abs(points) < np.array([35.0, 12.0, 8.0]) - 0.5, axis=1)
    assert not inside_bar.any()
    top = (np.abs(points[:, 2] - 8.0) < 1e-6) & (np.hypot(points[:, 0], points[:, 1]) > 9.5)
    assert top.sum() > 10 and np.allclose(normals[top], [0.0, 0.0, 1.0])  # outward
    again, _ = outer_surface_points(build_part(5))
    assert np.array_equal(points, again)  # seeded: one mesh, one metadata


def test_models_get_surface_points_beside_their_hull_points(tmp_path: Path):
    models_dir = write_builtin_models(tmp_path / "models")
    given = {"surface_points_mm": [[0.0, 0.0, 0.0]] * 16, "surface_normals": [[0.0, 0.0, 1.0]] * 16}
    objects = with_hull_points({3: {"diameter": 80.0}, 6: {"diameter": 70.0, **given}}, models_dir)
    surface = object_surface(objects[3])
    assert surface is not None and len(surface.points_mm) <= MAX_SURFACE_POINTS and "hull_points_mm" in objects[3]
    assert objects[6]["surface_points_mm"] == given["surface_points_mm"]  # kept as given
    with pytest.warns(UserWarning, match=r"objects \[6\]: their metadata has no surface_points_mm"):
        kept = with_hull_points({6: {"diameter": 70.0, "hull_points_mm": [[0.0, 0.0, 0.0]] * 4}}, tmp_path / "none")
    assert "surface_points_mm" not in kept[6]


def test_rendered_depth_places_parts_to_a_millimetre_given_the_true_rotation(tmp_path: Path):
    """Cluttered scenes (neighbours, occluders, the bin floor) with the industrial sensor's depth noise."""
    split_dir = render_cluttered_test_split(tmp_path / "scenes", scenes=2, size=(320, 240), sensor="industrial")
    split = read_bop_split(split_dir, split_dir / BUILTIN_MODELS_FOLDER, min_visib_fract=0.3)
    objects = with_hull_points(split.models_info, split.models_dir)
    errors_mm = []
    for inst in split.instances:
        info = objects[inst.obj_id]
        raw = read_depth(inst.depth_path)
        depth = check_depth(raw, raw.shape, inst.depth_scale)
        t_box = translation_from_box(inst.R_m2c, inst.box, inst.K, object_points_mm(info))
        t_depth, problem = translation_from_depth(inst.R_m2c, t_box, inst.K, depth, object_surface(info))
        assert problem is None, problem
        errors_mm.append(np.linalg.norm(t_depth - inst.t_m2c_mm))
    assert len(errors_mm) >= 8 and np.median(errors_mm) < 0.5 and max(errors_mm) < 1.5, np.round(errors_mm, 2)
