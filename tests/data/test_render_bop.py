"""Renderer and BOP reader together: what is rendered reads back with the right pose, box and mask."""

from __future__ import annotations

import gc
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

import popcode_trainer.data.render as render_module
import popcode_trainer.data.scene_render as scene_render_module
from popcode_runtime import PopcodeError
from popcode_runtime.geometry.camera import project_points
from popcode_trainer.data.bop import load_models_info, read_bop_split
from popcode_trainer.data.gl import DepthRenderer
from popcode_trainer.data.meshes import load_mesh
from popcode_trainer.data.objects import BUILTIN_PARTS, write_builtin_models
from popcode_trainer.data.render import (
    DEPTH_SCALE_MM,
    RECORDS_FOLDER,
    RenderSettings,
    parse_shard,
    render_split,
)


def _split_files(split: Path) -> dict[str, bytes]:
    """Every file of a split except the render marker, by relative path."""
    return {str(path.relative_to(split)): path.read_bytes() for path in sorted(split.rglob("*"))
            if path.is_file() and "models" not in path.parts and path.name != "popcode_render.json"}


def test_rendered_split_reads_back(builtin_split: Path) -> None:
    split = read_bop_split(builtin_split, builtin_split / "models")
    assert len(split.instances) == 3 * len(BUILTIN_PARTS)  # conftest renders 3 per object
    assert {instance.obj_id for instance in split.instances} == {part.obj_id for part in BUILTIN_PARTS}
    for instance in split.instances:
        assert instance.rendered and instance.visib_fract == 1.0
        image = cv2.imread(str(instance.image_path), cv2.IMREAD_UNCHANGED)
        assert image.shape == (128, 128) and image.dtype == np.uint8
        assert instance.depth_path.is_file() and instance.mask_visib_path.is_file()
        assert split.model_path(instance.obj_id).is_file()


def test_ground_truth_reprojects_onto_mask_and_box(builtin_split: Path) -> None:
    split = read_bop_split(builtin_split, builtin_split / "models")
    for instance in split.instances:
        vertices = load_mesh(split.model_path(instance.obj_id)).vertices
        pixels = project_points(vertices, instance.K, instance.R_m2c, instance.t_m2c_mm)
        mask = cv2.imread(str(instance.mask_visib_path), cv2.IMREAD_UNCHANGED) > 0
        grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        columns, rows = np.round(pixels).astype(int).T
        assert grown[rows, columns].mean() > 0.97
        ys, xs = np.nonzero(mask)  # the box is the BOP toolkit's: first pixel, distance to the last
        assert list(instance.box) == [xs.min(), ys.min(), xs.max() - xs.min(), ys.max() - ys.min()]
        # A pixel is drawn when its centre is covered, so the silhouette reaches at least the centres of the box's
        # first and last pixels (up to the rasteriser's 1/256 px); 4x multisampled depth, read from one sample off
        # the centre, broke this by up to 0.33 px.
        x, y, w, h = instance.box
        assert (pixels.min(axis=0) <= [x + 0.01, y + 0.01]).all()
        assert (pixels.max(axis=0) >= [x + w - 0.01, y + h - 0.01]).all()
        depth_mm = cv2.imread(str(instance.depth_path), cv2.IMREAD_UNCHANGED) * instance.depth_scale
        assert np.array_equal(depth_mm > 0, mask)
        z_mm = (vertices @ instance.R_m2c.T + instance.t_m2c_mm)[:, 2]
        assert z_mm.min() - 0.5 <= depth_mm[mask].min() and depth_mm[mask].max() <= z_mm.max() + 0.5


def test_depth_renderer_matches_written_depth(builtin_split: Path) -> None:
    split = read_bop_split(builtin_split, builtin_split / "models", obj_ids=[3])
    mesh = load_mesh(split.model_path(3))
    renderer = DepthRenderer(mesh.vertices, mesh.faces, 128, 128, opencv_pixel_centres=True)
    try:
        for instance in split.instances:
            depth_mm = renderer.render(instance.K, instance.R_m2c, instance.t_m2c_mm)
            written_mm = cv2.imread(str(instance.depth_path), cv2.IMREAD_UNCHANGED) * instance.depth_scale
            assert depth_mm.dtype == np.float32 and depth_mm.shape == (128, 128)
            assert np.array_equal(depth_mm > 0, written_mm > 0)  # both sampled at pixel centres
            mask = depth_mm > 0
            assert np.abs(depth_mm[mask] - written_mm[mask]).max() <= DEPTH_SCALE_MM / 2 + 1e-3
    finally:
        renderer.close()


def test_renderers_close_without_a_full_garbage_collection(builtin_split: Path) -> None:
    """pyrender's ``OffscreenRenderer.delete`` ends in ``gc.collect()``, a walk of every object alive: a quarter of
    a tiny demo's time went there, closing a renderer per model and split. popcode's renderers free their OpenGL
    context without it (automatic collections are off here; an explicit one would still run)."""
    mesh = load_mesh(read_bop_split(builtin_split, builtin_split / "models", obj_ids=[3]).model_path(3))
    makers = [lambda: DepthRenderer(mesh.vertices, mesh.faces, 64, 48), lambda: render_module._SceneRenderer(64, 48),
              lambda: scene_render_module._SceneRenderer(64, 48)]  # one at a time: each closes the EGL display
    full = []

    def count(phase: str, info: dict) -> None:
        if phase == "start" and info["generation"] == 2:
            full.append(info)

    for make in makers:
        renderer = make()
        gc.disable()
        gc.callbacks.append(count)
        try:
            renderer.close()
        finally:
            gc.callbacks.remove(count)
            gc.enable()
    assert full == []


def test_visib_fract_filter_and_box_choice(builtin_split: Path, tmp_path: Path) -> None:
    split_dir = shutil.copytree(builtin_split, tmp_path / "split")
    info_path = split_dir / "000003" / "scene_gt_info.json"
    info = json.loads(info_path.read_text())
    info["0"][0].update(visib_fract=0.3, bbox_visib=[1, 2, 3, 4])
    info["1"][0]["visib_fract"] = 0.6
    info_path.write_text(json.dumps(info))
    kept = read_bop_split(split_dir, split_dir / "models", obj_ids=[3])
    assert [instance.im_id for instance in kept.instances] == [1, 2]
    everything = read_bop_split(split_dir, split_dir / "models", obj_ids=[3], min_visib_fract=0.0, box="bbox_visib")
    assert everything.instances[0].box == (1.0, 2.0, 3.0, 4.0)
    with pytest.raises(PopcodeError, match="no instances"):
        read_bop_split(split_dir, split_dir / "models", obj_ids=[3], min_visib_fract=0.99 + 0.02)


def test_tless_layout_with_gray_tif_images(builtin_split: Path, tmp_path: Path) -> None:
    """A published T-LESS split: several objects per image, depth_scale from the camera file, no masks."""
    scene = tmp_path / "test_primesense" / "000001"
    (scene / "gray").mkdir(parents=True)
    cv2.imwrite(str(scene / "gray" / "000000.tif"), np.full((540, 720), 128, np.uint8))
    R = np.eye(3).ravel().tolist()
    (scene / "scene_gt.json").write_text(json.dumps({"0": [
        {"cam_R_m2c": R, "cam_t_m2c": [0, 0, 700], "obj_id": 3},
        {"cam_R_m2c": R, "cam_t_m2c": [50, 0, 700], "obj_id": 6}]}))
    (scene / "scene_gt_info.json").write_text(json.dumps({"0": [
        {"bbox_obj": [10, 10, 50, 40], "bbox_visib": [10, 10, 50, 40], "visib_fract": 0.9},
        {"bbox_obj": [100, 10, 50, 40], "bbox_visib": [-1, -1, -1, -1], "visib_fract": 0.0}]}))
    (scene / "scene_camera.json").write_text(json.dumps({"0": {
        "cam_K": [1075.6, 0, 360, 0, 1073.9, 270, 0, 0, 1], "depth_scale": 0.1}}))
    split = read_bop_split(tmp_path / "test_primesense", builtin_split / "models")
    (instance,) = split.instances
    assert instance.obj_id == 3 and instance.image_path.suffix == ".tif" and not instance.rendered
    assert instance.mask_visib_path is None and instance.depth_scale == 0.1
    assert instance.K[0, 0] == pytest.approx(1075.6)


@pytest.mark.parametrize(("file", "edit", "message"), [
    ("000001/scene_gt.json", lambda text: text[:-5], "scene_gt.json is not valid JSON"),
    ("000001/scene_camera.json", lambda text: text.replace('"cam_K"', '"K"'), "scene_camera.json: key 'cam_K'"),
    ("000001/scene_gt.json", lambda text: text.replace('"cam_t_m2c"', '"t"'), "scene_gt.json: key 'cam_t_m2c'"),
    ("models/models_info.json", lambda text: text.replace('"diameter"', '"d"'), "models_info.json: key 'diameter'"),
])
def test_malformed_json_names_file_and_key(builtin_split: Path, tmp_path: Path, file, edit, message) -> None:
    split_dir = shutil.copytree(builtin_split, tmp_path / "split")
    path = split_dir / file
    path.write_text(edit(path.read_text()))
    with pytest.raises(PopcodeError, match=message):
        read_bop_split(split_dir, split_dir / "models")


def test_missing_json_and_unknown_object(builtin_split: Path, tmp_path: Path) -> None:
    split_dir = shutil.copytree(builtin_split, tmp_path / "split")
    (split_dir / "000002" / "scene_gt_info.json").unlink()
    with pytest.raises(PopcodeError, match="missing file .*000002/scene_gt_info.json"):
        read_bop_split(split_dir, split_dir / "models")
    with pytest.raises(PopcodeError, match=r"object ids \[99\] are not in"):
        read_bop_split(builtin_split, builtin_split / "models", obj_ids=[99])
    with pytest.raises(PopcodeError, match="missing file .*models_info.json"):
        load_models_info(tmp_path)


def test_bad_model_file_and_bad_shard(tmp_path: Path) -> None:
    broken = tmp_path / "obj_000001.ply"
    broken.write_text("ply\nformat nonsense\n")
    with pytest.raises(PopcodeError, match="cannot load model|no triangles"):
        load_mesh(broken)
    for text in ("2/2", "a/b", "1"):
        with pytest.raises(PopcodeError, match="shard"):
            parse_shard(text)


@pytest.fixture(scope="module")
def models_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_builtin_models(tmp_path_factory.mktemp("models"))


SMALL = RenderSettings(images_per_object=3, width=64, height=64, seed=7)


def test_shards_are_disjoint_and_merge_into_the_unsharded_split(models_dir: Path, tmp_path: Path) -> None:
    whole = render_split(models_dir, tmp_path / "whole", SMALL, obj_ids=[1, 6], progress=False)
    shards = [render_split(models_dir, tmp_path / f"shard{i}", SMALL, obj_ids=[1, 6], shard=(i, 2), progress=False)
              for i in range(2)]
    records = [{str(p.relative_to(shard)) for p in shard.rglob(f"{RECORDS_FOLDER}/*.json")} for shard in shards]
    assert records[0] and records[1] and not records[0] & records[1]
    merged = tmp_path / "merged"
    for i in range(2):  # both shards write into one folder, as processes on one machine would
        render_split(models_dir, merged, SMALL, obj_ids=[1, 6], shard=(i, 2), progress=False)
    assert _split_files(merged) == _split_files(whole)


def test_interrupted_render_completes_on_rerun(models_dir: Path, tmp_path: Path, monkeypatch) -> None:
    whole = render_split(models_dir, tmp_path / "whole", SMALL, obj_ids=[2], progress=False)
    original, calls = render_module._render_one, []

    def interrupted(*args, **kwargs) -> None:
        if len(calls) == 2:
            raise KeyboardInterrupt
        calls.append(args[3])
        original(*args, **kwargs)

    monkeypatch.setattr(render_module, "_render_one", interrupted)
    with pytest.raises(KeyboardInterrupt):
        render_split(models_dir, tmp_path / "again", SMALL, obj_ids=[2], progress=False)
    assert not list((tmp_path / "again").rglob("*.tmp"))
    calls.clear()
    monkeypatch.setattr(render_module, "_render_one", lambda *args, **kwargs: (calls.append(args[3]),
                                                                              original(*args, **kwargs)))
    render_split(models_dir, tmp_path / "again", SMALL, obj_ids=[2], progress=False)
    assert calls == [2]  # only the missing image
    assert _split_files(tmp_path / "again") == _split_files(whole)
    with pytest.raises(PopcodeError, match="other settings"):
        render_split(models_dir, tmp_path / "again", RenderSettings(images_per_object=3, seed=8), obj_ids=[2])


def test_a_shard_of_other_objects_under_the_same_ids_is_refused(models_dir: Path, tmp_path: Path) -> None:
    """Shards must render the same objects: a mesh changed between two shards names what differs, not merged."""
    other = tmp_path / "other_models"
    shutil.copytree(models_dir, other)
    mesh = load_mesh(other / "obj_000002.ply")
    mesh.apply_scale(1.01)
    (other / "obj_000002.ply").write_bytes(mesh.export(file_type="ply", encoding="binary"))
    render_split(models_dir, tmp_path / "split", SMALL, obj_ids=[2], shard=(0, 2), progress=False)
    with pytest.raises(PopcodeError, match=r"other settings \(objects: "):
        render_split(other, tmp_path / "split", SMALL, obj_ids=[2], shard=(1, 2), progress=False)


def test_builtin_models_never_replace_other_models(tmp_path: Path) -> None:
    folder = write_builtin_models(tmp_path / "models")
    assert write_builtin_models(folder) == folder  # the same parts again: nothing changes
    (folder / "models_info.json").write_text("{}")
    with pytest.raises(PopcodeError, match="holds other models than the built-in parts"):
        write_builtin_models(folder)
    assert (folder / "models_info.json").read_text() == "{}"
