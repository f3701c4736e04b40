"""Issue 19's catalogue for ``popcode-train``: bad files, folders and settings end in one line and exit 2."""

from __future__ import annotations

import io
import json
import os
import pickle
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
import trimesh
from hostile_cases import error_lines, refused_in_one_line, run_cli
from hostile_files import write_hostile_files
from onnx_models import linear_model, save

from popcode_runtime import CodeLayout, ModelMetadata, PopulationCode, Representation, symmetry_rotations
from popcode_runtime.geometry.rotations import axis_angle_to_matrix
from popcode_trainer.cli import main
from popcode_trainer.data.objects import model_info
from popcode_trainer.train.checkpoint import TRAINED_KEYS


def _about(axis: tuple[float, float, float], *angles_deg: float) -> list[list[float]]:
    """BOP ``symmetries_discrete`` rotations about an axis through the origin."""
    result = []
    for angle in angles_deg:
        matrix = np.eye(4)
        matrix[:3, :3] = axis_angle_to_matrix(np.asarray(axis, float), np.deg2rad(angle))
        result.append(matrix.ravel().tolist())
    return result


# models folder -> (mesh, declared symmetries); "bar_2fold" is right, the others are wrong for their mesh
MODELS = {
    "bar_2fold": (lambda: trimesh.creation.box((60.0, 30.0, 10.0)), {"symmetries_discrete": _about((0, 0, 1), 180)}),
    "flange_4fold": (lambda: trimesh.creation.box((60.0, 30.0, 10.0)),
                     {"symmetries_discrete": _about((0, 0, 1), 90, 180, 270)}),
    "nut_generator": (lambda: trimesh.creation.cylinder(radius=20.0, height=8.0, sections=6),
                      {"symmetries_discrete": _about((0, 0, 1), 60)}),
    "rod_axis_x": (lambda: trimesh.creation.cylinder(radius=8.0, height=50.0, sections=64),
                   {"symmetries_continuous": [{"axis": [1, 0, 0], "offset": [0, 0, 0]}]}),
    "bar_wrong_flip": (lambda: trimesh.creation.box((60.0, 30.0, 10.0)),
                       {"symmetries_discrete": _about((1, 1, 0), 180)}),
}

_PLY = ("ply\nformat ascii 1.0\nelement vertex {count}\nproperty float x\nproperty float y\nproperty float z\n"
        "element face {faces}\nproperty list uchar int vertex_indices\nend_header\n{vertices}\n{triangles}\n")
_BOX_INFO = {"diameter": 17.4, "min_x": -5, "min_y": -5, "min_z": -5, "size_x": 10, "size_y": 10, "size_z": 10}


def _ply(vertices: str, triangles: str = "3 0 1 2\n3 0 2 3") -> str:
    """An ASCII PLY of the given vertex lines and triangles, as a hand or a broken exporter writes it."""
    return _PLY.format(count=len(vertices.splitlines()), faces=len(triangles.splitlines()), vertices=vertices,
                       triangles=triangles)


# models folder -> (obj_000001.ply text, models_info.json entry of object 1): meshes no renderer can use
BROKEN_MODELS = {
    "mesh_bad_index": (_ply("0 0 0\n10 0 0\n0 10 0", "3 0 1 7"), _BOX_INFO),
    "mesh_nan_vertex": (_ply("0 0 0\n10 0 0\nnan 10 0\n0 0 10"), _BOX_INFO),
    "mesh_inf_vertex": (_ply("0 0 0\n10 0 0\ninf 10 0\n0 0 10"), _BOX_INFO),
    "mesh_one_point": (_ply("1 1 1\n1 1 1\n1 1 1\n1 1 1"), _BOX_INFO),
    "mesh_on_a_line": (_ply("0 0 0\n5 0 0\n10 0 0\n20 0 0"), _BOX_INFO),
    "mesh_off_centre": (_ply("1000 0 0\n1010 0 0\n1000 10 0\n1000 0 10"), _BOX_INFO),
    "mesh_diameter_tiny": (_ply("-5 -5 -5\n5 -5 -5\n-5 5 -5\n-5 -5 5"), {**_BOX_INFO, "diameter": 1e-6}),
    "mesh_not_ply": ("not a mesh\n", _BOX_INFO),
}

# split folder -> (image width and height [px], cam_R_m2c, bbox_obj, cx = cy [px]); "split" is right
SPLITS = {
    "split": ((128, 128), np.eye(3).ravel().tolist(), [10, 10, 40, 40], 64.0),
    "split_nan_pose": ((128, 128), [float("nan")] + np.eye(3).ravel().tolist()[1:], [10, 10, 40, 40], 64.0),
    "split_scaled_pose": ((128, 128), (2 * np.eye(3)).ravel().tolist(), [10, 10, 40, 40], 64.0),
    "split_image_small_for_box": ((48, 48), np.eye(3).ravel().tolist(), [60, 60, 40, 40], 24.0),
    "split_image_small_for_camera": ((32, 32), np.eye(3).ravel().tolist(), [10, 10, 20, 20], 64.0),
    "split_box_huge": ((128, 128), np.eye(3).ravel().tolist(), [0, 0, 1e9, 1e9], 64.0),
    "split_focal_zero": ((128, 128), np.eye(3).ravel().tolist(), [10, 10, 40, 40], 64.0),
}
FOCAL_PX = {"split_focal_zero": 0.0}  # cam_K's fx and fy; 500 px elsewhere


def _write_models(folder: Path, name: str) -> None:
    build, symmetries = MODELS[name]
    (folder / name).mkdir()
    mesh = build()
    mesh.export(folder / name / "obj_000001.ply")
    (folder / name / "models_info.json").write_text(json.dumps({"1": model_info(mesh, symmetries)}))


def _write_broken_models(folder: Path, name: str) -> None:
    text, info = BROKEN_MODELS[name]
    (folder / name).mkdir()
    (folder / name / "obj_000001.ply").write_text(text)
    (folder / name / "models_info.json").write_text(json.dumps({"1": info}))


def _write_box_fit_models(folder: Path) -> None:
    """Two ONNX models of bar_2fold's object 1: one with hull points, one with neither hull points nor 3-D box."""
    info = json.loads((folder / "bar_2fold" / "models_info.json").read_text())["1"]
    layout = CodeLayout(n_axes=42, n_angles=12)
    bias = PopulationCode(layout).encode(np.eye(3), symmetry_rotations(info))
    hull = {**info, "hull_points_mm": [[x, y, z] for x in (-30, 30) for y in (-15, 15) for z in (-5, 5)]}
    bare = {key: value for key, value in info.items() if not key.startswith(("min_", "size_"))}
    (folder / "box_fit").mkdir()
    for name, entry in (("hull", hull), ("bare", bare)):
        metadata = ModelMetadata(representation=Representation.POPULATION_CODE, code=layout, objects={1: entry})
        save(linear_model(bias, metadata=metadata), folder / "box_fit" / f"{name}.onnx")


def _write_split(folder: Path, name: str) -> None:
    """One image with one annotated instance of object 1, as BOP writes it."""
    (width, height), R, box, centre = SPLITS[name]
    scene = folder / name / "000000"
    (scene / "rgb").mkdir(parents=True)
    cv2.imwrite(str(scene / "rgb" / "000000.png"), np.full((height, width), 128, np.uint8))
    pose = {"obj_id": 1, "cam_R_m2c": R, "cam_t_m2c": [0, 0, 500]}
    (scene / "scene_gt.json").write_text(json.dumps({"0": [pose]}))
    (scene / "scene_gt_info.json").write_text(json.dumps({"0": [{"bbox_obj": box, "visib_fract": 1.0}]}))
    focal = FOCAL_PX.get(name, 500.0)
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [focal, 0, centre, 0, focal, centre, 0, 0,
                                                                         1]}}))


def _render(files: Path, models: str) -> list[str]:
    return ["render", "--objects", str(files / models), "--images", "1", "--out", str(files / f"{models}_render")]


def _train(files: Path, models: str = "bar_2fold", split: str = "split") -> list[str]:
    return ["train", "--set", f'data.splits=["{files / split}"]', "--set", f'data.models_dir="{files / models}"',
            "--set", f'train.out_dir="{files / models}_{split}_run"', "--set", "data.val_fraction=0",
            "--set", "data.augment=false"]


class NotPlainData:
    """An object whose pickle needs this class: weights_only loading refuses it."""


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("hostile_trainer")
    (folder / "junk.pt").write_bytes(b"\x00not a checkpoint")
    torch.save(torch.zeros(3), folder / "tensor.pt")
    torch.save({"model": {}, "config": {}}, folder / "partial.pt")
    torch.save({**{key: {} for key in TRAINED_KEYS}, "metadata": [1, 2]}, folder / "list_metadata.pt")
    with (folder / "pickled.pt").open("wb") as handle:
        torch.save({"model": NotPlainData()}, handle, pickle_module=pickle)
    torch.save({**{key: {} for key in TRAINED_KEYS}, "epoch": 0, "best_val_error_deg": 0.0}, folder / "keys.pt")
    np.savez(folder / "arrays.npz", a=np.zeros(3))
    np.save(folder / "nan_crops.npy", np.full((4, 1, 128, 128), np.nan, np.float32))
    np.save(folder / "flat_crops.npy", np.zeros((4, 128, 128), np.float32))
    np.save(folder / "bright_crops.npy", np.full((4, 1, 128, 128), 3.0, np.float32))
    np.save(folder / "empty_crops.npy", np.zeros((0, 1, 128, 128), np.float32))
    np.save(folder / "good_crops.npy", np.zeros((4, 1, 128, 128), np.float32))
    np.save(folder / "object_crops.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(folder / "float_ids.npy", np.array([1.5, 2.0, 3.0, 4.0]))
    (folder / "not_npy.npy").write_text("text")
    (folder / "a_folder").mkdir()
    (folder / "config.toml").write_text("[data]\nsplits = ['nowhere']\n")
    write_hostile_files(folder / "runtime")  # a population-code and a single-variable ONNX model among them
    for name in MODELS:
        _write_models(folder, name)
    for name in SPLITS:
        _write_split(folder, name)
    for name in BROKEN_MODELS:
        _write_broken_models(folder, name)
    _write_box_fit_models(folder)
    return folder


def _export(files: Path, *extra: str, checkpoint: str = "keys.pt", out: str = "out.onnx") -> list[str]:
    return ["export", str(files / checkpoint), "--out", str(files / out), *extra]


CASES = [
    ("export-junk", lambda f: _export(f, checkpoint="junk.pt"), "cannot read checkpoint"),
    ("export-missing", lambda f: _export(f, checkpoint="missing.pt"), "checkpoint not found"),
    ("export-folder-as-checkpoint", lambda f: _export(f, checkpoint="a_folder"), "checkpoint not found"),
    ("export-tensor", lambda f: _export(f, checkpoint="tensor.pt"), "holds a Tensor"),
    ("export-partial", lambda f: _export(f, checkpoint="partial.pt"), "is not a popcode training checkpoint"),
    ("export-list-metadata", lambda f: _export(f, checkpoint="list_metadata.pt"), "are not dicts"),
    ("export-pickled", lambda f: _export(f, checkpoint="pickled.pt"), "not a trusted popcode checkpoint"),
    ("export-npz", lambda f: _export(f, checkpoint="arrays.npz"), "cannot read checkpoint"),
    ("export-out-folder", lambda f: _export(f, out="a_folder"), "is a folder"),
    ("export-out-is-the-checkpoint", lambda f: _export(f, out="keys.pt"), "is the input"),
    ("export-out-nowhere", lambda f: _export(f, out="no/such/model.onnx"), "does not exist"),
    ("export-crops-nan", lambda f: _export(f, "--crops", str(f / "nan_crops.npy"), "--quantize", "int8"), "NaN"),
    ("export-crops-3d", lambda f: _export(f, "--crops", str(f / "flat_crops.npy")), "must be float [N >= 1"),
    ("export-crops-range", lambda f: _export(f, "--crops", str(f / "bright_crops.npy")), "must lie in [0, 1]"),
    ("export-crops-empty", lambda f: _export(f, "--crops", str(f / "empty_crops.npy")), "must be float [N >= 1"),
    ("export-crops-objects", lambda f: _export(f, "--crops", str(f / "object_crops.npy")), "not a .npy array"),
    ("export-crops-text", lambda f: _export(f, "--crops", str(f / "not_npy.npy")), "not a .npy array"),
    ("export-crops-npz", lambda f: _export(f, "--crops", str(f / "arrays.npz")), ".npz archive"),
    ("export-crops-missing", lambda f: _export(f, "--crops", str(f / "none.npy")), "crops file not found"),
    ("export-crop-ids-float", lambda f: _export(f, "--crops", str(f / "good_crops.npy"), "--crop-obj-ids",
                                                str(f / "float_ids.npy")), "must be 4 integers"),
    ("export-ids-without-crops", lambda f: _export(f, "--crop-obj-ids", str(f / "float_ids.npy")), "give --crops"),
    ("evaluate-split-is-a-file", lambda f: ["evaluate", str(f / "keys.pt"), "--split", str(f / "keys.pt"),
                                            "--models-dir", str(f / "a_folder")], "is a file, not a folder"),
    ("evaluate-models-dir-is-a-file", lambda f: ["evaluate", str(f / "keys.pt"), "--split", str(f / "a_folder"),
                                                 "--models-dir", str(f / "keys.pt")], "is a file, not a folder"),
    ("render-out-is-a-file", lambda f: ["render", "--objects", "builtin", "--images", "1", "--out", str(f / "keys.pt")],
     "is a file"),
    ("render-objects-missing", lambda f: ["render", "--images", "1", "--out", str(f / "r"), "--objects",
                                          str(f / "none")], "no such models folder"),
    ("preview-count-zero", lambda f: ["preview", "--split", str(f), "--out", str(f / "p.png"), "--count", "0"],
     "--count must be at least 1"),
    ("preview-count-negative", lambda f: ["preview", "--split", str(f), "--out", str(f / "p.png"), "--count", "-1"],
     "--count must be at least 1"),
    ("preview-out-is-a-folder", lambda f: ["preview", "--split", str(f / "split"), "--models", str(f / "bar_2fold"),
                                           "--out", str(f / "a_folder")], "a_folder is a folder, not a file"),
    ("preview-split-is-a-file", lambda f: ["preview", "--split", str(f / "keys.pt"), "--out", str(f / "p.png")],
     "is a file, not a folder"),
    ("render-symmetry-wrong-4fold", lambda f: _render(f, "flange_4fold"),
     "symmetries_discrete[0] (rotation 90.0 deg about (0, 0, 1)) does not map the mesh onto itself"),
    ("render-symmetry-generator-alone", lambda f: _render(f, "nut_generator"), "not closed under composition"),
    ("render-symmetry-wrong-axis", lambda f: _render(f, "rod_axis_x"), "symmetries_continuous[0] (axis (1, 0, 0)"),
    ("render-symmetry-wrong-flip", lambda f: _render(f, "bar_wrong_flip"), "does not map the mesh onto itself"),
    ("train-symmetry-wrong-4fold", lambda f: _train(f, "flange_4fold"), "of the diameter away from the surface"),
    ("train-symmetry-generator-alone", lambda f: _train(f, "nut_generator"), "declare all 5 non-identity"),
    ("evaluate-refined-single-variable", lambda f: ["evaluate", str(f / "runtime/model.onnx"),
                                                    str(f / "runtime/single_variable.onnx"),
                                                    "--split", str(f / "a_folder"), "--models-dir", str(f / "a_folder"),
                                                    "--decoder", "refined"],
     "single_variable.onnx: the refined decoder needs a population-code model, this one is single_variable"),
    ("train-split-nan-pose", lambda f: _train(f, split="split_nan_pose"),
     "scene_gt.json is not valid JSON: NaN is not a JSON number"),  # the one JSON reader refuses it
    ("train-split-scaled-pose", lambda f: _train(f, split="split_scaled_pose"), "is not a rotation matrix"),
    ("train-split-image-small-for-box", lambda f: _train(f, split="split_image_small_for_box"),
     "is 48x48 px but the box [60.0, 60.0, 40.0, 40.0] of scene 0, image 0, object 0 (scene_gt_info.json)"),
    ("train-split-image-small-for-camera", lambda f: _train(f, split="split_image_small_for_camera"),
     "puts the principal point at (64, 64), outside it"),
    *((f"render-{name.replace('_', '-')}", lambda f, name=name: _render(f, name), expect) for name, expect in (
        ("mesh_bad_index", "a triangle names vertex 7, but the file has 3 vertices"),
        ("mesh_nan_vertex", "vertex coordinates contain NaN or inf"),
        ("mesh_inf_vertex", "vertex coordinates contain NaN or inf"),
        ("mesh_one_point", "mesh_one_point/obj_000001.ply is degenerate: its 2 triangles have no area"),
        ("mesh_on_a_line", "mesh_on_a_line/obj_000001.ply is degenerate"),
        ("mesh_off_centre", "reaches 1010 mm from its origin, more than its diameter 17.4 mm"),
        ("mesh_diameter_tiny", "more than its diameter 1e-06 mm in models_info.json"),
        ("mesh_not_ply", "cannot load model"),
    )),
    ("render-objects-is-a-checkpoint", lambda f: ["render", "--objects", str(f / "keys.pt"), "--images", "1",
                                                  "--out", str(f / "r")], "no such models folder"),
    ("export-crops-nan-float-only", lambda f: _export(f, "--crops", str(f / "nan_crops.npy")),
     "no agreement can be judged"),
    ("evaluate-out-is-a-file", lambda f: ["evaluate", str(f / "box_fit/hull.onnx"), "--split", str(f / "split"),
                                          "--models-dir", str(f / "bar_2fold"), "--out", str(f / "keys.pt")],
     "keys.pt is not a folder (a file, link or FIFO); give a folder for the report"),
    ("evaluate-translation-without-box-fit-points", lambda f: [
        "evaluate", str(f / "box_fit/hull.onnx"), str(f / "box_fit/bare.onnx"), "--split", str(f / "split"),
        "--models-dir", str(f / "bar_2fold"), "--translation", "--out", str(f / "eval")],
     "bare.onnx: no points to fit a box to: object 1: object metadata lacks 'min_x'"),
    ("evaluate-min-visib-fract-nan", lambda f: [
        "evaluate", str(f / "box_fit/hull.onnx"), "--split", str(f / "split"), "--models-dir", str(f / "bar_2fold"),
        "--min-visib-fract", "nan", "--out", str(f / "eval")], "min_visib_fract must be a number >= 0, got nan"),
    ("evaluate-depth-split-without-depth", lambda f: [
        "evaluate", str(f / "box_fit/hull.onnx"), "--split", str(f / "split"), "--models-dir", str(f / "bar_2fold"),
        "--depth", "--out", str(f / "eval")], "instances have no depth image (first: "),
    ("evaluate-refine-without-depth", lambda f: [
        "evaluate", str(f / "box_fit/hull.onnx"), "--split", str(f / "split"), "--models-dir", str(f / "bar_2fold"),
        "--refine", "--out", str(f / "eval")], "--refine refines each pose against its image's depth: add --depth"),
    ("evaluate-threads-negative", lambda f: [
        "evaluate", str(f / "box_fit/hull.onnx"), "--split", str(f / "split"), "--models-dir", str(f / "bar_2fold"),
        "--threads", "-1", "--out", str(f / "eval")], "threads must be >= 0, got -1"),
    ("train-min-visib-fract-nan", lambda f: [*_train(f), "--set", "data.min_visib_fract=nan"],
     "data.min_visib_fract must be a finite number, got nan"),
    ("train-lr-nan", lambda f: ["train", "--set", "train.lr=nan"], "train.lr must be a finite number, got nan"),
    ("train-val-fraction-inf", lambda f: ["train", "--set", "data.val_fraction=inf"], "must be a finite number"),
    ("train-seed-negative", lambda f: ["train", "--set", "train.seed=-1"], "train.seed must lie in [0, 2^63)"),
    ("train-workers-negative", lambda f: ["train", "--set", "data.num_workers=-3"], "num_workers must be at least 0"),
    ("train-crop-size-zero", lambda f: ["train", "--set", "data.crop_size=0"], "data.crop_size must lie in [8, 1024]"),
    ("train-hypotheses-zero", lambda f: ["train", "--set", "train.num_hypotheses=0"], "num_hypotheses must be at"),
    ("train-conv-too-wide", lambda f: ["train", "--set", "network.conv_channels=[100000, 4, 4]"], "at most 4096 wide"),
    ("train-dense-too-large", lambda f: [*_train(f), "--set", "network.hidden=[100000000, 8, 8]"],
     "dense parameters, more than the limit of 1,000,000,000"),
    ("train-one-crop-per-batch-at-1x1", lambda f: [*_train(f), "--set", "data.crop_size=8", "--set",
                                                   "train.batch_size=1"], "BatchNorm needs two crops per rank"),
    ("render-size-huge", lambda f: ["render", "--objects", "builtin", "--images", "1", "--out", str(f / "r"),
                                    "--size", "100000", "100000"], "at most 8192 px a side"),
    # Bounded before any work: a billion scenes used to list (and stat) every image before writing one.
    ("render-scenes-a-billion", lambda f: ["render", "--objects", "builtin", "--scenes", "1000000000", "--out",
                                           str(f / "r")], "scenes must lie in [1, 1000000], got 1000000000"),
    ("render-images-a-billion", lambda f: ["render", "--objects", "builtin", "--images", "1000000000", "--out",
                                           str(f / "r")], "images per object must lie in [1, 1000000]"),
    ("render-seed-negative", lambda f: ["render", "--objects", "builtin", "--images", "1", "--seed", "-1", "--out",
                                        str(f / "r")], "seed must lie in [0, 2**62), got -1"),
    ("render-scenes-seed-negative", lambda f: ["render", "--objects", "builtin", "--scenes", "1", "--seed", "-1",
                                               "--out", str(f / "r")], "seed must lie in [0, 2**62), got -1"),
    *((f"render-bin-size-{value}", lambda f, value=value: [
        "render", "--objects", "builtin", "--scenes", "1", "--bin-size-mm", value, "--out", str(f / "r")],
       f"0 <= bin_size_mm <= 100000 and 0 < visib_delta_mm <= 100000, got 35.0, {shown} and")
      for value, shown in (("nan", "nan"), ("inf", "inf"), ("-3.0", "-3.0"), ("1e9", "1000000000.0"))),
    *((f"render-empty-share-{value}", lambda f, value=value: [
        "render", "--objects", "builtin", "--scenes", "1", "--empty-share", value, "--out", str(f / "r")],
       f"empty_share (--empty-share: the share of images without parts) must lie in [0, 1], got {shown}")
      for value, shown in (("nan", "nan"), ("-0.1", "-0.1"), ("1.5", "1.5"))),
    # A split whose parts are too small to see used to be written and exit 0.
    ("render-scenes-nothing-visible", lambda f: ["render", "--objects", "builtin", "--scenes", "1", "--size", "64",
                                                 "48", "--bin-size-mm", "100000", "--out", str(f / "specks")],
     "scene image 0: no target part is visible in 10 draws of the bin"),
    ("train-split-box-huge", lambda f: _train(f, split="split_box_huge"),
     "scene 0, image 0, object 0 (scene_gt_info.json): box (0.0, 0.0, 1000000000.0, 1000000000.0) is larger than 4x"),
    ("train-split-focal-zero", lambda f: _train(f, split="split_focal_zero"),
     "scene_camera.json: 'cam_K' in image 0: not a valid camera matrix (focal lengths must be positive"),
    ("evaluate-split-box-huge", lambda f: ["evaluate", str(f / "box_fit/hull.onnx"), "--split",
                                           str(f / "split_box_huge"), "--models-dir", str(f / "bar_2fold"),
                                           "--out", str(f / "eval")],
     "scene 0, image 0, object 0 (scene_gt_info.json): box (0.0, 0.0, 1000000000.0, 1000000000.0) is larger than 4x "
     "the 128x128 image"),
    ("train-negative-conv", lambda f: ["train", "--set", "network.conv_channels=[-8, 16, 16]"],
     "network.conv_channels widths must be at least 1"),
    ("train-zero-hidden", lambda f: ["train", "--set", "network.hidden=[0, 16, 16]"], "network.hidden widths"),
    ("train-zero-kernel", lambda f: ["train", "--set", "network.conv_kernel=0"], "network.conv_kernel must be"),
    ("train-config-missing", lambda f: ["train", "--config", str(f / "none.toml")], "config file not found"),
    ("train-unknown-key", lambda f: ["train", "--set", "train.speed=3"], "unknown config key"),
]


# issue 50: bounds and declarations
_BAR = trimesh.creation.box((60.0, 30.0, 10.0))  # its diameter, the box's diagonal: 67.8233 mm
_HALF_TURN_Z = _about((0, 0, 1), 180)[0]


def _checked(files: Path, name: str, mesh_ply: str | None = None, objects: int = 1, **entry: object) -> list[str]:
    """``demo --check`` of a models folder of the bar (or of a PLY text) whose entries are the bar's, changed."""
    folder = files / f"bounds_{name}"
    if not folder.is_dir():
        folder.mkdir()
        if mesh_ply is None:
            _BAR.export(folder / "obj_000001.ply")
        else:
            (folder / "obj_000001.ply").write_text(mesh_ply)
        info = {**model_info(_BAR, {}), **entry}
        (folder / "models_info.json").write_text(json.dumps({str(k): info for k in range(1, objects + 1)}))
    return ["demo", "--objects", str(folder), "--check"]


CASES += [
    ("demo-objects-over-the-limit", lambda f: _checked(f, "objects", objects=10_001),
     "lists 10001 objects; at most 10000 are allowed"),
    ("demo-symmetries-counted-before-read", lambda f: _checked(f, "discrete_1001", symmetries_discrete=[
        _HALF_TURN_Z] * 1000 + ["abc"]), "object 1: symmetries_discrete lists 1001 symmetries; at most 1000"),
    ("demo-continuous-counted-before-read", lambda f: _checked(f, "continuous_4", symmetries_continuous=[
        {"axis": [0, 0, 1]}] * 3 + ["abc"]), "object 1: symmetries_continuous lists 4 symmetries; at most 3"),
    ("demo-symmetry-listed-twice", lambda f: _checked(f, "repeat", symmetries_discrete=[_HALF_TURN_Z] * 2),
     "symmetries_discrete[1] (rotation 180.0 deg about (0, 0, 1)) repeats symmetries_discrete[0]; list each"),
    ("demo-identity-listed", lambda f: _checked(f, "identity", symmetries_discrete=[np.eye(4).ravel().tolist()]),
     "symmetries_discrete[0] (rotation 0.0 deg about"),
    ("demo-symmetry-numbers-as-text", lambda f: _checked(f, "text_matrix", symmetries_discrete=[
        [str(v) for v in _HALF_TURN_Z]]), "symmetries_discrete[0] is not a list of numbers: got ['-1.0', "),
    ("demo-diameter-as-text", lambda f: _checked(f, "diameter_text", diameter="71"),
     "key 'diameter' of object 1 must be a positive number, got '71' (str); its mesh's diameter is 67.8233 mm"),
    ("demo-diameter-true", lambda f: _checked(f, "diameter_true", diameter=True),
     "must be a positive number, got True (bool); its mesh's diameter is 67.8233 mm"),
    ("demo-extent-true", lambda f: _checked(f, "size_true", size_x=True), "object 1: size_x must be a number"),
    ("demo-extent-as-text", lambda f: _checked(f, "min_text", min_z="-5"), "object 1: min_z must be a number"),
    ("demo-diameter-smaller", lambda f: _checked(f, "diameter_smaller", diameter=40.7),
     "diameter 40.7 mm in models_info.json is smaller than the mesh's 67.8233 mm (the largest distance between two "
     "of its vertices) by more than 2 %: set it to 67.8233"),
    ("demo-diameter-larger", lambda f: _checked(f, "diameter_larger", diameter=71.2),
     "diameter 71.2 mm in models_info.json is larger than the mesh's 67.8233 mm"),
    ("demo-ply-header-claims-billions", lambda f: _checked(f, "ply_billions", mesh_ply=_ply(
        "0 0 0\n10 0 0\n0 10 0\n0 0 10").replace("element vertex 4", "element vertex 3000000000")),
     "its header claims 3,000,000,000 vertex elements; at most 4,000,000 are allowed: decimate the mesh"),
    ("demo-ply-header-claims-more-than-the-file", lambda f: _checked(f, "ply_truncated", mesh_ply=_ply(
        "0 0 0\n10 0 0\n0 10 0\n0 0 10").replace("element vertex 4", "element vertex 1000000")),
     "its header claims 1,000,000 vertex, 2 face elements, more than its 43 bytes of data hold"),
    ("demo-epochs-1e20", lambda f: ["demo", "--check", "--epochs", "100000000000000000000"],
     "--epochs must be at most 100,000, got 100,000,000,000,000,000,000"),
    ("demo-images-1e7", lambda f: ["demo", "--check", "--images", "10000000"],
     "--images must be at most 1,000,000, got 10,000,000"),
    ("train-epochs-1e18", lambda f: ["train", "--set", "train.epochs=1000000000000000000"],
     "train.epochs must be at most 100,000 (the paper trains 80), got 1,000,000,000,000,000,000"),
    # issue 62: a value argparse refuses is one line too, not its usage block
    ("pretrain-epochs-1e20", lambda f: ["pretrain", "--epochs", "1e20"],
     "popcode-train pretrain: error: argument --epochs: invalid int value: '1e20' (see popcode-train pretrain --help)"),
    ("demo-epochs-1e20", lambda f: ["demo", "--epochs", "1e20"],
     "popcode-train demo: error: argument --epochs: invalid int value: '1e20' (see popcode-train demo --help)"),
]


# issue 50: one writer, evaluate's output
def _occupied(lock: Path, fifo: bool = False) -> Path:
    """``lock``'s folder, with a folder (or a FIFO, whose open would wait for a writer) where a command keeps its
    lock file."""
    lock.parent.mkdir(exist_ok=True)
    if fifo and not lock.is_fifo():
        os.mkfifo(lock)
    elif not fifo:
        lock.mkdir(exist_ok=True)
    return lock.parent


def _evaluate_hull(files: Path, out: Path, *options: str) -> list[str]:
    return ["evaluate", str(files / "box_fit/hull.onnx"), "--split", str(files / "split"), "--models-dir",
            str(files / "bar_2fold"), "--out", str(out), *options]


CASES += [
    ("render-shard-lock-is-a-folder", lambda f: ["render", "--objects", "builtin", "--images", "1", "--out",
                                                 str(_occupied(f / "render_lock_folder" / ".render-0-of-1.lock"))],
     ".render-0-of-1.lock is not a regular file; remove it (it is where the lock is kept)"),
    ("train-run-lock-is-a-fifo", lambda f: [
        *_train(f), "--set", f'train.out_dir="{_occupied(f / "train_lock_fifo" / "train.lock", fifo=True)}"'],
     "train.lock is not a regular file; remove it"),
    ("export-lock-is-a-folder", lambda f: _export(f, out=str(_occupied(f / "export_lock" / "out.onnx.lock")
                                                             / "out.onnx")), "out.onnx.lock is not a regular file"),
    ("evaluate-lock-is-a-fifo", lambda f: _evaluate_hull(f, _occupied(f / "evaluate_lock_fifo" / "evaluate.lock",
                                                                      fifo=True)),
     "evaluate.lock is not a regular file (a link, device or FIFO)"),
]


# issue 62: the detector's trainer and the commands that write beside their inputs
SHIPPED = Path(__file__).resolve().parents[2] / "models"


def _flipped(source: Path, target: Path) -> Path:
    """``source`` with 4 KiB of its largest tensor's bytes inverted: an archive torch.load still reads."""
    with zipfile.ZipFile(source) as archive:
        largest = max(archive.infolist(), key=lambda entry: entry.file_size)
    data = bytearray(source.read_bytes())
    start = largest.header_offset + 1024  # past the entry's local header, inside its bytes
    data[start:start + 4096] = bytes(255 - value for value in data[start:start + 4096])
    target.write_bytes(bytes(data))
    return target


def _flipped_init(files: Path, setting: str, shipped: str, name: str) -> str:
    """``--set`` of ``setting`` to a copy of the shipped start ``shipped`` with flipped bytes."""
    return f'{setting}="{_flipped(SHIPPED / shipped, files / name)}"'


def _detector(files: Path, *options: str, split: str = "split", out: str | None = None) -> list[str]:
    return ["train-detector", "--split", str(files / split), "--out", out or str(files / "detector_run"), "--quiet",
            *options]


def _kit(files: Path, out: str, hours: str = "1") -> list[str]:
    return ["kit", "--objects", str(files / "bar_2fold"), "--out", out, "--hours", hours]


CASES += [
    *((f"train-detector-{key}-{value}", lambda f, key=key, value=value: _detector(f, "--set",
                                                                                   f"detector.{key}={value}"),
       f"detector.{key} must be {kind}, got {shown}") for key, value, kind, shown in (
        ("lr", "abc", "float", "'abc'"), ("head_convs", "1.5", "int", "1.5"), ("batch_size", "2.5", "int", "2.5"),
        ("fpn_channels", "64.0", "int", "64.0"), ("seed", '"x"', "int", "'x'"), ("epochs", "1.5", "int", "1.5"),
        ("widths", "[8, 8, 16, 16, 16.5]", "int", "16.5"), ("init", "5", "str", "5"),
        ("val_fraction", "true", "float", "True"))),
    ("train-detector-val-fraction-leaves-no-training-image",
     lambda f: _detector(f, "--from-scratch", "--set", "detector.val_fraction=0.99"),
     "detector.val_fraction 0.99 holds out 1 of the 1 annotated images, leaving none to train on"),
    ("train-detector-val-fraction-holds-out-the-one-image",
     lambda f: _detector(f, "--from-scratch", "--set", "detector.val_fraction=0.1"),
     "detector.val_fraction 0.1 holds out 1 of the 1 annotated images, leaving none to train on: lower it (0: no"),
    ("train-detector-obj-ids-the-split-lacks", lambda f: _detector(f, "--from-scratch", "--obj-ids", "1", "99"),
     "--obj-ids: the splits hold no instance of object 99; they hold objects 1"),
    ("train-detector-out-in-its-split", lambda f: _detector(f, out=str(f / "split" / "detector")),
     "split/detector lies in the input"),
    ("train-out-dir-in-its-split", lambda f: [*_train(f), "--set", f'train.out_dir="{f / "split" / "run"}"'],
     "split/run lies in the input"),
    ("path-trace-out-in-its-split", lambda f: ["path-trace", "--split", str(f / "split"), "--out",
                                               str(f / "split" / "pt")], "lies in the input"),
    ("path-trace-out-is-its-split", lambda f: ["path-trace", "--split", str(f / "split"), "--out", str(f / "split")],
     "is the input"),
    ("render-out-in-its-models", lambda f: ["render", "--objects", str(f / "bar_2fold"), "--images", "1", "--out",
                                            str(f / "bar_2fold" / "rendered")], "lies in the input"),
    ("demo-out-in-its-objects", lambda f: ["demo", "--objects", str(f / "bar_2fold"), "--out",
                                           str(f / "bar_2fold" / "demo")], "lies in the input"),
    *((f"kit-hours-{name}", lambda f, hours=hours: _kit(f, str(f / "kit"), hours), expect) for name, hours, expect in (
        ("nan", "nan", "--hours must be a positive number of hours, not nan"),
        ("negative", "-1", "--hours must be a positive number of hours, not -1"),
        ("too-few", "0.05", "too little to train anything: a kit needs at least 0.2 h (12 minutes"),
        ("absurd", "1e9", "--hours 1e+09 is more than a kit can use: at most 168"))),
    ("kit-out-in-its-objects", lambda f: _kit(f, str(f / "bar_2fold" / "kit")), "lies in the input"),
    ("kit-out-holds-other-files", lambda f: _kit(f, str(f)), "holds files that are not a popcode kit's"),
    ("kit-out-is-a-file", lambda f: _kit(f, str(f / "junk.pt")), "is a file, not a folder"),
    ("train-detector-start-with-flipped-bytes",
     lambda f: _detector(f, "--set", _flipped_init(f, "detector.init", "detector-start-e855fe97f1.pt",
                                                   "detector_start_flipped.pt")),
     "detector_start_flipped.pt is damaged: its part .detector-start.pt/data/"),
    ("train-pretrained-start-with-flipped-bytes",
     lambda f: [*_train(f), "--set", _flipped_init(f, "train.init", "pretrained-start-ac55e87b5a.pt",
                                                   "pose_start_flipped.pt")],
     "pose_start_flipped.pt is damaged: its part "),
    ("pretrain-fewer-crops-than-a-batch", lambda f: ["pretrain", "--out", str(f / "pretrain_small"), "--parts", "1",
                                                     "--images", "1", "--scenes", "0", "--epochs", "2"],
     "fewer than one batch (32): raise --images, --parts or --scenes"),
]



def test_evaluate_refuses_an_out_it_cannot_write_before_any_prediction(files: Path, monkeypatch) -> None:
    """An --out to be made in a folder this user may not write is refused before the first image is predicted, not
    when the report is written. The tests run as root, whom permissions do not stop: the system's answer for
    another user is given."""
    def predicted(*args, **kwargs):
        raise AssertionError("a prediction ran before --out was checked")

    read_only = files / "read_only"
    read_only.mkdir(exist_ok=True)
    access = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kwargs: path != read_only and access(path, mode, **kwargs))
    monkeypatch.setattr("popcode_trainer.eval.pipeline.models.predict_rotations", predicted)
    stderr = io.StringIO()
    monkeypatch.setattr("sys.stderr", stderr)
    assert main(_evaluate_hull(files, read_only / "eval")) == 2
    assert error_lines(stderr.getvalue()) == [f"popcode-train: error: --out {read_only / 'eval'}: folder {read_only} "
                                              "is not writable"]


def test_a_refused_render_writes_nothing(files, monkeypatch):
    """Options are checked before the built-in models are written into the new split."""
    stderr = io.StringIO()
    monkeypatch.setattr("sys.stderr", stderr)
    out = files / "refused_render"
    for options in (["--scenes", "2", "--bin-size-mm", "nan"], ["--images", "1", "--obj-ids", "99"]):
        assert main(["render", "--objects", "builtin", *options, "--out", str(out)]) == 2
        assert not out.exists(), stderr.getvalue()
    other = files / "rendered_from_other_models"
    other.mkdir()
    (other / "popcode_render.json").write_text("{}")  # a split of other meshes: no models/ folder inside
    assert main(["render", "--objects", "builtin", "--images", "1", "--out", str(other)]) == 2
    assert "was rendered from other models" in stderr.getvalue() and not (other / "models").exists()
    unmarked = files / "unmarked_split" / "000000"
    unmarked.mkdir(parents=True)  # a split whose settings file is lost: its images' settings are unknown
    assert main(["render", "--objects", "builtin", "--images", "1", "--out", str(unmarked.parent)]) == 2
    assert "holds files but no popcode_render.json" in stderr.getvalue()
    fifo = files / "fifo_models" / "models" / "obj_000001.ply"
    fifo.parent.mkdir(parents=True)
    os.mkfifo(fifo)  # a rename would replace it, an open wait for a writer
    assert main(["render", "--objects", "builtin", "--images", "1", "--out", str(files / "fifo_models")]) == 2
    assert "is not a regular file" in stderr.getvalue() and fifo.is_fifo()


@pytest.mark.parametrize(("argv", "expect"), [case[1:] for case in CASES], ids=[case[0] for case in CASES])
def test_popcode_train_refuses_in_one_line(argv, expect, files):
    code, _, stderr = run_cli(argv(files), main)
    assert refused_in_one_line(code, stderr, expect), stderr
    assert not list(files.glob("*.onnx")) and not list(files.glob(".*.tmp"))  # nothing half-written left behind


def test_evaluate_checks_every_model_before_any_prediction(files, monkeypatch):
    """A model that cannot serve --translation is named before the first image is predicted, not after hours."""
    def predicted(*args, **kwargs):
        raise AssertionError("a prediction ran before every model was checked")

    monkeypatch.setattr("popcode_trainer.eval.pipeline.models.predict_rotations", predicted)
    stderr = io.StringIO()
    monkeypatch.setattr("sys.stderr", stderr)
    argv = ["evaluate", str(files / "box_fit/hull.onnx"), str(files / "box_fit/bare.onnx"), "--split",
            str(files / "split"), "--models-dir", str(files / "bar_2fold"), "--translation", "--out", str(files / "e")]
    assert main(argv) == 2 and "bare.onnx: no points to fit a box to" in stderr.getvalue()
