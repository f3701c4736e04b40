"""Cluttered scene renders: masks and visibility as the BOP toolkit defines them, shards, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from popcode_runtime import PopcodeError
from popcode_runtime.base.files import write_bytes_atomic, write_json_atomic
from popcode_trainer.cli import main
from popcode_trainer.data.bop import RENDER_MARKER, read_bop_split
from popcode_trainer.data.gl import DepthRenderer
from popcode_trainer.data.meshes import load_mesh
from popcode_trainer.data.objects import model_info
from popcode_trainer.data.scene_annotation import instance_gt_info
from popcode_trainer.data.scene_content import Layouts, SceneContent, SceneSettings
from popcode_trainer.data.scene_layout import PlacedObject
from popcode_trainer.data.scene_render import empty_image, render_emptied_scenes, render_scene_split
from popcode_trainer.metrics.visibility import depth_to_distance

TINY = SceneSettings(scenes=4, width=96, height=72, seed=3, parts=(3, 5), distractors=(1, 2), bin_size_mm=90.0)


def _write_models(folder: Path, meshes: dict[int, trimesh.Trimesh]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for obj_id, mesh in meshes.items():
        write_bytes_atomic(folder / f"obj_{obj_id:06d}.ply", mesh.export(file_type="ply", encoding="binary"))
    write_json_atomic(folder / "models_info.json", {str(k): model_info(m, {}) for k, m in meshes.items()})
    return folder


@pytest.fixture(scope="module")
def tiny_models(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A flat block and a short cylinder, about 30 mm."""
    return _write_models(tmp_path_factory.mktemp("scene_models"), {
        1: trimesh.creation.box(extents=(32.0, 20.0, 10.0)),
        2: trimesh.creation.cylinder(radius=9.0, height=24.0, sections=16),
    })


@pytest.fixture(scope="module")
def tiny_scenes(tiny_models: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("scenes")
    render_scene_split(tiny_models, out, TINY, progress=False)
    return out


def _read(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)


def _box(mask: np.ndarray) -> list[int]:
    ys, xs = np.nonzero(mask)
    return [int(xs.min()), int(ys.min()), int(xs.max() - xs.min()), int(ys.max() - ys.min())] if len(xs) else [-1] * 4


def test_masks_and_visibility_match_a_rerender_of_each_part(tiny_models: Path, tiny_scenes: Path) -> None:
    """mask = the part rendered alone; mask_visib = mask minus what a nearer surface hides by more than 15 mm."""
    scene = tiny_scenes / "000000"
    gts, infos, cameras = (json.loads((scene / f"scene_{name}.json").read_text())
                           for name in ("gt", "gt_info", "camera"))
    assert sorted(gts) == ["0", "1", "2", "3"]
    alone_mm: dict[tuple[str, int], np.ndarray] = {}
    wide_mm: dict[tuple[str, int], np.ndarray] = {}  # on a 3x larger image, centred on this one (the toolkit's)
    for obj_id in (1, 2):
        mesh = load_mesh(tiny_models / f"obj_{obj_id:06d}.ply")
        for scale, rendered in ((1, alone_mm), (3, wide_mm)):  # one OpenGL context at a time: they share a display
            renderer = DepthRenderer(mesh.vertices, mesh.faces, scale * TINY.width, scale * TINY.height,
                                     opencv_pixel_centres=True)
            try:
                for im_id, gt_list in gts.items():
                    K = np.array(cameras[im_id]["cam_K"]).reshape(3, 3)
                    K[:2, 2] += (scale - 1) / 2 * np.array([TINY.width, TINY.height])
                    for index, gt in enumerate(gt_list):
                        if gt["obj_id"] == obj_id:
                            rendered[im_id, index] = renderer.render(K, np.array(gt["cam_R_m2c"]).reshape(3, 3),
                                                                     gt["cam_t_m2c"])
            finally:
                renderer.close()
    partly_hidden = cut_by_border = 0
    for im_id, gt_list in gts.items():
        K = np.array(cameras[im_id]["cam_K"]).reshape(3, 3)
        scene_depth_mm = _read(scene / "depth" / f"{int(im_id):06d}.png") * cameras[im_id]["depth_scale"]
        alone = [alone_mm[im_id, index] for index in range(len(gt_list))]
        for index, (depth_mm, info) in enumerate(zip(alone, infos[im_id], strict=True)):
            stem = f"{int(im_id):06d}_{index:06d}.png"
            mask, visib = _read(scene / "mask" / stem) > 0, _read(scene / "mask_visib" / stem) > 0
            assert np.array_equal(mask, depth_mm > 0)
            assert not (visib & ~mask).any()
            others = np.stack([d if j != index else np.zeros_like(d) for j, d in enumerate(alone)])
            nearer_part = ((others > 0) & (others < depth_mm - 16.0)).any(axis=0)  # 1 mm beyond the tolerance
            assert not (visib & mask & nearer_part).any(), "a pixel hidden by a nearer part counts as visible"
            distance_scene, distance_part = depth_to_distance(scene_depth_mm, K), depth_to_distance(depth_mm, K)
            hidden = mask & ~visib
            assert (distance_part[hidden] - distance_scene[hidden] > 15.0 - 0.1).all()
            assert (distance_part[visib] - distance_scene[visib] <= 15.0 + 0.1).all()
            assert info["px_count_visib"] == visib.sum() and info["bbox_visib"] == _box(visib)
            whole = wide_mm[im_id, index] > 0
            assert info["px_count_all"] == whole.sum() >= mask.sum()
            if visib.any():
                x, y, w, h = _box(whole)
                assert info["bbox_obj"] == [x - TINY.width, y - TINY.height, w, h]
            cut_by_border += bool(whole.sum() > mask.sum())
            assert info["visib_fract"] == pytest.approx(info["px_count_visib"] / info["px_count_all"])
            if visib.any():
                x, y, w, h = info["bbox_visib"]
                ox, oy, ow, oh = info["bbox_obj"]
                assert ox <= x and oy <= y and x + w <= ox + ow and y + h <= oy + oh
            partly_hidden += 0 < info["visib_fract"] < 1
    assert partly_hidden > 0, "the tiny scenes should show some occlusion"
    assert cut_by_border > 0, "the tiny scenes should show some part cut by the image border"


def test_scene_split_reads_back_with_either_box(tiny_models: Path, tiny_scenes: Path) -> None:
    everything = read_bop_split(tiny_scenes, tiny_models, min_visib_fract=0.0)
    assert {instance.obj_id for instance in everything.instances} <= {1, 2}
    visible = read_bop_split(tiny_scenes, tiny_models, min_visib_fract=0.6, box="bbox_visib")
    assert 0 < len(visible.instances) <= len(everything.instances)
    assert all(instance.visib_fract >= 0.6 and instance.mask_visib_path.is_file() for instance in visible.instances)


def test_a_fully_hidden_part_gets_visib_fract_0_and_is_skipped(tiny_models: Path, tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    """A block held flat 30 mm above a standing cylinder, seen from straight above, hides it completely
    (BOP counts what lies less than 15 mm behind the surface in front as visible)."""
    settings = SceneSettings(scenes=1, width=64, height=48, seed=0, parts=(2, 2), distractors=(0, 0), bin=False,
                             sensor="none")
    down = np.diag([1.0, -1.0, -1.0])  # camera axes in the world: looking down the world's -z
    content = SceneContent(
        targets=[PlacedObject(2, np.eye(3), np.array([0.0, 0.0, 12.0])),
                 PlacedObject(1, np.eye(3), np.array([0.0, 0.0, 59.0]))],
        distractors=[], distractor_meshes={}, walls=[], ground_side_mm=400.0,
        R_w2c=down, t_w2c_mm=-down @ np.array([0.0, 0.0, 300.0]))
    monkeypatch.setattr(Layouts, "draw", lambda self, rng, K: content)
    render_scene_split(tiny_models, tmp_path, settings, progress=False)
    info = json.loads((tmp_path / "000000" / "scene_gt_info.json").read_text())["0"]
    assert info[0]["visib_fract"] == 0 and info[0]["px_count_visib"] == 0 and info[0]["px_count_all"] > 0
    assert info[0]["bbox_visib"] == [-1, -1, -1, -1] and info[0]["bbox_obj"] == [-1, -1, -1, -1]
    assert info[1]["visib_fract"] == 1.0
    split = read_bop_split(tmp_path, tiny_models, min_visib_fract=0.6)
    assert [(instance.obj_id, instance.gt_index) for instance in split.instances] == [(1, 1)]


def test_nothing_visible_gives_zero_counts_and_no_box() -> None:
    K = np.array([[50.0, 0.0, 15.5], [0.0, 50.0, 11.5], [0.0, 0.0, 1.0]])
    nothing = np.zeros((24, 32), np.float32)
    mask, visib, info = instance_gt_info(nothing, nothing, K, 15.0)
    assert not mask.any() and not visib.any()
    assert info["visib_fract"] == 0.0 and info["bbox_obj"] == info["bbox_visib"] == [-1, -1, -1, -1]


def _split_files(split: Path) -> dict[str, bytes]:
    return {str(path.relative_to(split)): path.read_bytes() for path in sorted(split.rglob("*"))
            if path.is_file() and path.name != "popcode_render.json"}


def test_shards_are_disjoint_and_merge_into_the_unsharded_render(tiny_models: Path, tmp_path: Path) -> None:
    """With empty images too (images 1 and 3 of four at share 0.5): each shard draws the same ones."""
    settings = SceneSettings(scenes=4, width=48, height=40, seed=5, parts=(2, 3), distractors=(1, 2),
                             bin_size_mm=90.0, empty_share=0.5)
    whole = tmp_path / "whole"
    render_scene_split(tiny_models, whole, settings, progress=False)
    done = []
    for index in range(2):
        stats = render_scene_split(tiny_models, tmp_path / f"shard{index}", settings, shard=(index, 2),
                                   progress=False)
        done.append({p.name for p in (tmp_path / f"shard{index}").rglob(".popcode_records/*.json")})
        assert stats.images == len(done[-1])
    assert done == [{"000000.json", "000002.json"}, {"000001.json", "000003.json"}]
    _check_empty_images(tiny_models, whole, settings, {1: True, 3: False})
    assert json.loads((whole / RENDER_MARKER).read_text())["empty_share"] == 0.5
    merged = tmp_path / "merged"
    for index in range(2):
        render_scene_split(tiny_models, merged, settings, shard=(index, 2), progress=False)
    assert _split_files(merged) == _split_files(whole)
    assert render_scene_split(tiny_models, merged, settings, progress=False).images == 0  # nothing left to do
    with pytest.raises(PopcodeError, match="other settings"):
        render_scene_split(tiny_models, merged, SceneSettings(scenes=3, width=48, height=40, seed=6), progress=False)


def _check_empty_images(models: Path, split: Path, settings: SceneSettings, empty: dict[int, bool]) -> None:
    """The images ``empty`` names (with whether they keep their distractors) list no object, have no mask and are
    the split's emptied scenes pixel for pixel; the others hold parts; the pose reader finds no crop in them."""
    scene = split / "000000"
    gts, infos = (json.loads((scene / f"{name}.json").read_text()) for name in ("scene_gt", "scene_gt_info"))
    for k in range(settings.scenes):
        assert (gts[str(k)] == [] and infos[str(k)] == []) == (k in empty)
        assert any((scene / "mask_visib").glob(f"{k:06d}_*.png")) == (k not in empty)
    for k, keep_distractors in empty.items():
        frame = render_emptied_scenes(models, settings, [k], keep_distractors)[0]
        assert frame.tobytes() == _read(scene / "gray" / f"{k:06d}.png").tobytes()
    crops = read_bop_split(split, models, min_visib_fract=0.0).instances
    assert {instance.im_id for instance in crops} == set(range(settings.scenes)) - set(empty)


def test_empty_share_is_exact_spread_and_half_without_distractors() -> None:
    for scenes, share in ((10, 0.2), (7, 0.5), (20, 0.35), (5, 1.0), (5, 0.0)):
        drawn = [empty_image(k, share) for k in range(scenes)]
        empties = [keep for keep in drawn if keep is not None]
        assert len(empties) == int(scenes * share)
        assert empties.count(True) == (len(empties) + 1) // 2  # alternating, the first with its distractors


def test_one_part_is_enough(tmp_path: Path) -> None:
    models = _write_models(tmp_path / "models", {7: trimesh.creation.box(extents=(20.0, 14.0, 8.0))})
    render_scene_split(models, tmp_path / "split", SceneSettings(scenes=1, width=48, height=40, parts=(3, 3)),
                       progress=False)
    gts = json.loads((tmp_path / "split" / "000000" / "scene_gt.json").read_text())["0"]
    assert [gt["obj_id"] for gt in gts] == [7, 7, 7]
    # no empty images, no entry: a split made before --empty-share existed is completed by the same settings
    assert "empty_share" not in json.loads((tmp_path / "split" / RENDER_MARKER).read_text())


def test_bad_input_is_one_clear_error(tiny_models: Path, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code = main(["render", "--objects", str(tiny_models), "--out", str(tmp_path / "full"), "--scenes", "1",
                 "--size", "48", "40", "--parts", "60", "60", "--bin-size-mm", "80", "--quiet"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "do not fit into a bin" in lines[0]
    for mixed in (["--images", "2", "--sensor", "webcam"], ["--scenes", "2", "--random-position"]):
        assert main(["render", "--objects", str(tiny_models), "--out", str(tmp_path / "mixed"), *mixed]) == 2
        assert "only with" in capsys.readouterr().err
    assert not (tmp_path / "mixed").exists()
    flat = _write_models(tmp_path / "flat", {1: trimesh.creation.box(extents=(10.0, 10.0, 10.0))})
    (flat / "obj_000001.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                         "property float y\nproperty float z\nelement face 0\n"
                                         "property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    with pytest.raises(PopcodeError, match="no triangles"):
        render_scene_split(flat, tmp_path / "flat_split", SceneSettings(scenes=1, width=32, height=32),
                           progress=False)
    for bad in ({"parts": (0, 2)}, {"parts": (3, 2)}, {"fill_range": (0.0, 1.0)}, {"max_tilt_deg": 90.0},
                {"sensor": "fisheye"}, {"scenes": 0}, {"width": 100_000}, {"empty_share": -0.1},
                {"empty_share": 1.5}, {"empty_share": float("nan")}):
        with pytest.raises(PopcodeError):
            SceneSettings(**{"scenes": 1, **bad})
    # the command's one line for a bad --empty-share: tests/trainer/test_hostile_trainer_inputs.py
    assert main(["render", "--objects", str(tiny_models), "--out", str(tmp_path / "share"), "--images", "2",
                 "--empty-share", "0.5"]) == 2
    assert "only with --scenes" in capsys.readouterr().err
    assert not (tmp_path / "share").exists()


def test_an_emptied_scene_is_its_bin_without_its_parts(tiny_models, tiny_scenes):
    """The frames a detector should find nothing on: image k's bin, camera, lights and distractors, no part; where
    no part lay, the split's own image pixel for pixel."""
    emptied = render_emptied_scenes(tiny_models, TINY, [0, 1], keep_distractors=True)
    bare = render_emptied_scenes(tiny_models, TINY, [0], keep_distractors=False)[0]
    assert render_emptied_scenes(tiny_models, TINY, [1], keep_distractors=True)[0].tobytes() == emptied[1].tobytes()
    for k, frame in enumerate(emptied):
        assert frame.shape == (TINY.height, TINY.width) and frame.dtype == np.uint8
        shown = _read(tiny_scenes / "000000" / "gray" / f"{k:06d}.png")
        parts = np.zeros(frame.shape, bool)
        for mask in (tiny_scenes / "000000" / "mask").glob(f"{k:06d}_*.png"):
            parts |= _read(mask) > 0
        parts = cv2.dilate(parts.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert parts.any() and (frame[~parts] == shown[~parts]).all()
        assert (frame[parts] != shown[parts]).mean() > 0.5
    assert (bare != emptied[0]).any(), "every image holds a distractor (TINY): without it the frame differs"
    with pytest.raises(PopcodeError, match="needs its bin walls"):
        render_emptied_scenes(tiny_models, SceneSettings(1, width=96, height=72, bin=False), [0], True)
