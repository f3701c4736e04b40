"""Scene renders draw each instance alone only over its own region: the same masks, depth and annotations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

import popcode_trainer.data.scene_render as scene_module
from popcode_trainer.data.gl import CentreSampledDepth, gl_pose, import_pyrender, offscreen, pyrender_camera
from popcode_trainer.data.objects import write_builtin_models
from popcode_trainer.data.render import camera_matrix
from popcode_trainer.data.scene_content import SceneSettings
from popcode_trainer.data.scene_render import render_scene_split


def test_a_region_is_the_crop_of_the_whole_image_bit_for_bit() -> None:
    pyrender = import_pyrender()
    width, height = 96, 72
    context = offscreen(width, height)
    depth = CentreSampledDepth(context, width, height)
    try:
        mesh = trimesh.creation.icosphere(subdivisions=2, radius=30.0)
        depth.scene.add(pyrender.Mesh.from_trimesh(mesh, smooth=False),
                        pose=gl_pose(np.eye(3), np.array([65.0, -10.0, 200.0])))  # cut by the right border
        depth.scene.add(pyrender_camera(pyrender, camera_matrix(width, height), 40.0, 200.0), pose=np.eye(4))
        whole = depth.render()
        assert (whole > 0).sum() > 100 and (whole[:, -1] > 0).any()
        for x0, y0, x1, y1 in [(50, 10, 96, 60), (0, 0, 96, 72), (60, 30, 61, 31), (3, 4, 40, 9), (10, 10, 10, 20)]:
            part = depth.render((x0, y0, x1, y1))
            assert part.dtype == np.float32 and np.array_equal(part, whole[y0:y1, x0:x1])
        assert np.array_equal(depth.render(), whole)  # the whole image again: nothing of a region is left over
        with pytest.raises(ValueError, match="not inside"):
            depth.render((90, 0, 97, 10))
    finally:
        depth.delete()
        context.delete()


def _written(split: Path) -> dict[str, bytes]:
    """Every file of the split but the images: the colour pass varies by a pixel here and there from run to
    run, with or without regions (see bench/results/scene-render-speed.md); no depth pass does."""
    return {str(path.relative_to(split)): path.read_bytes() for path in sorted(split.rglob("*"))
            if path.is_file() and path.parent.name not in ("gray", "rgb") and path.name != "popcode_render.json"}


def test_scenes_are_written_as_with_whole_image_renders(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The built-in parts in seeded scenes, near enough for the border to cut some: every mask, depth and
    annotation is the same as when each instance is rendered over the whole image (as before regions)."""
    models = write_builtin_models(tmp_path / "models")
    settings = SceneSettings(scenes=4, width=240, height=180, seed=11, fill_range=(1.0, 1.6))
    regions = []
    covered_region = scene_module._covered_region

    def recorded(*args: object, **kwargs: object) -> object:
        regions.append(covered_region(*args, **kwargs))
        return regions[-1]

    monkeypatch.setattr(scene_module, "_covered_region", recorded)
    render_scene_split(models, tmp_path / "regions", settings, progress=False)
    monkeypatch.setattr(scene_module, "_covered_region", lambda *args, **kwargs: None)  # the whole image
    render_scene_split(models, tmp_path / "whole", settings, progress=False)

    assert _written(tmp_path / "regions") == _written(tmp_path / "whole")
    areas = [(x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in regions]
    assert len(areas) > 20 and np.median(areas) < 0.2 * settings.width * settings.height
    infos = json.loads((tmp_path / "regions" / "000000" / "scene_gt_info.json").read_text())
    instances = [info for image in infos.values() for info in image]
    cut = [info for info in instances if info["px_count_visib"] and (
        min(info["bbox_obj"][:2]) < 0 or info["bbox_obj"][0] + info["bbox_obj"][2] >= settings.width
        or info["bbox_obj"][1] + info["bbox_obj"][3] >= settings.height)]
    assert cut, "some part should be cut by the image border: the 3x larger render counts its whole silhouette"
    assert any(0 < info["visib_fract"] < 1 for info in instances)
