"""A BOP split's layout as both halves read it: scene folders, images, cameras, ground-truth boxes.

The format is the BOP toolkit's (``docs/bop_datasets_format.md``): a split holds
scene folders ``000000, 000001, ...``, each with ``rgb/`` or ``gray/`` images named
by image id, ``scene_camera.json`` (``cam_K`` row-major), ``scene_gt.json`` and
``scene_gt_info.json`` (one entry per object instance, in the same order). The
trainer's reader (:mod:`popcode_trainer.data.bop`) builds on these functions;
``popcode run`` uses them to find the images and cameras of a detections file.
"""

from __future__ import annotations

import os
from collections.abc import Container, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..base.checks import number
from ..base.errors import PopcodeError
from ..base.files import name_id, read_json, require_folder
from ..geometry.camera import MAX_DEPTH_SCALE, MIN_DEPTH_SCALE, parse_camera_matrix

IMAGE_FOLDERS = ("rgb", "gray")
BOX_KINDS = ("bbox_obj", "bbox_visib")
BOP19_MIN_VISIB_FRACT = 0.1  # the BOP19 test targets: at least 10 % of the object visible


def json_field(entry: Any, key: str, path: Path, where: str, size: int | None = None) -> Any:
    """``entry[key]`` (as a finite float array of ``size`` numbers when size is given), else an error naming it."""
    if not isinstance(entry, Mapping) or key not in entry:
        raise PopcodeError(f"{path}: key '{key}' missing in {where}")
    value = entry[key]
    if size is None:
        return value
    try:
        array = np.asarray(value, dtype=np.float64).reshape(size)
    except (TypeError, ValueError, OverflowError) as error:
        raise PopcodeError(f"{path}: key '{key}' in {where} must be {size} numbers, got {value!r}") from error
    if not np.isfinite(array).all():
        raise PopcodeError(f"{path}: key '{key}' in {where} contains NaN or inf")
    return array


def unique_ids(names: Iterable[str], what: str) -> dict[int, str]:
    """Id -> name for the names that are ids; two names of one id (``1`` and ``000001``) are refused."""
    ids: dict[int, str] = {}
    for name in names:
        found = name_id(name)
        if found is None:
            continue
        if found in ids:
            raise PopcodeError(f"{what}: '{ids[found]}' and '{name}' both stand for id {found}; keep one")
        ids[found] = name
    return ids


def int_keys(data: Any, path: Path) -> dict[int, Any]:
    """A JSON object keyed by integer ids (``"3": ...``) as a dict keyed by int."""
    if not isinstance(data, Mapping):
        raise PopcodeError(f"{path}: expected a JSON object keyed by id, got {type(data).__name__}")
    bad = next((key for key in data if name_id(key) is None), None)
    if bad is not None:
        raise PopcodeError(f"{path}: keys must be integer ids (digits 0-9), got {bad[:40]!r}")
    return {found: data[name] for found, name in unique_ids(data, str(path)).items()}


def bop_id(entry: Any, key: str, path: Path, where: str) -> int:
    """``entry[key]`` as an id: a JSON integer >= 0; ``1.7``, ``"1"``, ``[1]`` or ``true`` are named, not coerced."""
    value = json_field(entry, key, path, where)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise PopcodeError(f"{path}: key '{key}' in {where} must be a non-negative integer, got {value!r}")
    return value


def folder_index(folder: Path) -> dict[str, Path]:
    """File stem -> path for every file in a folder (one listdir instead of a stat per image)."""
    if not folder.is_dir():
        return {}
    files: dict[str, Path] = {}
    for name in os.listdir(folder):
        stem = name.rsplit(".", 1)[0]
        if name.startswith("."):
            continue
        if stem in files:
            raise PopcodeError(f"{folder}: '{files[stem].name}' and '{name}' are two files of one image; keep one")
        files[stem] = folder / name
    return files


def scene_folders(split_dir: Path) -> list[Path]:
    """The split's scene folders in id order; a folder without any is not a BOP split."""
    require_folder(split_dir, "split folder")
    folders = unique_ids((path.name for path in split_dir.iterdir() if path.is_dir()), f"scene folders of {split_dir}")
    scenes = [split_dir / folders[scene_id] for scene_id in sorted(folders)]
    if not scenes:
        raise PopcodeError(f"{split_dir} has no scene folders (000000, 000001, ...); is it a BOP split?")
    return scenes


def image_folder(scene_dir: Path) -> Path:
    """The scene's ``rgb/`` or ``gray/`` folder."""
    folder = next((scene_dir / name for name in IMAGE_FOLDERS if (scene_dir / name).is_dir()), None)
    if folder is None:
        raise PopcodeError(f"{scene_dir} has no image folder; expected one of {list(IMAGE_FOLDERS)}")
    return folder


def read_cam_K(camera: Any, path: Path, im_id: int) -> np.ndarray:
    """``cam_K`` of one ``scene_camera.json`` entry as 3x3, checked as the runtime checks a camera (positive focal
    lengths, last row 0 0 1): a corrupt camera is named here, not trained or evaluated on."""
    values = json_field(camera, "cam_K", path, f"image {im_id}", size=9)
    try:
        return parse_camera_matrix(values)
    except PopcodeError as error:
        raise PopcodeError(f"{path}: 'cam_K' in image {im_id}: {error}") from error


def read_depth_scale(camera: Any, path: Path, im_id: int) -> float:
    """``depth_scale`` (mm per depth unit, default 1) of one ``scene_camera.json`` entry, checked as the runtime
    checks one."""
    value = camera.get("depth_scale", 1.0) if isinstance(camera, Mapping) else 1.0
    try:
        return number(value, "depth_scale", MIN_DEPTH_SCALE, MAX_DEPTH_SCALE)
    except PopcodeError as error:
        raise PopcodeError(f"{path}: image {im_id}: {error}") from error


@dataclass(frozen=True)
class SplitImage:
    """One image of a split, its camera (None where the split has no ``scene_camera.json``) and its depth image
    (None where the split has none) with its ``depth_scale`` (None where its ``scene_camera.json`` entry gives none:
    BOP's format puts it there for every split with depth, and no default is right for all of them)."""

    scene_id: int
    im_id: int
    path: Path
    K: np.ndarray | None
    depth_path: Path | None = None
    depth_scale: float | None = None  # mm per depth unit


def split_images(split_dir: str | Path) -> dict[tuple[int, int], SplitImage]:
    """Every image of the split by ``(scene_id, im_id)``, with its camera matrix and depth image where the split
    has them."""
    images: dict[tuple[int, int], SplitImage] = {}
    for scene_dir in scene_folders(Path(split_dir)):
        scene_id = int(scene_dir.name)
        camera_path = scene_dir / "scene_camera.json"
        cameras = int_keys(read_json(camera_path), camera_path) if camera_path.is_file() else {}
        files = folder_index(image_folder(scene_dir))
        depths = folder_index(scene_dir / "depth")
        depth_ids = unique_ids(depths, f"depth images of {scene_dir}")
        for im_id, stem in sorted(unique_ids(files, f"images of {scene_dir}").items()):
            path = files[stem]
            K = read_cam_K(cameras[im_id], camera_path, im_id) if im_id in cameras else None
            depth_path = depths[depth_ids[im_id]] if im_id in depth_ids else None
            scaled = depth_path is not None and im_id in cameras and "depth_scale" in cameras[im_id]
            depth_scale = read_depth_scale(cameras[im_id], camera_path, im_id) if scaled else None
            images[(scene_id, im_id)] = SplitImage(scene_id, im_id, path, K, depth_path, depth_scale)
    return images


def _where(im_id: int, gt_index: int) -> str:
    return f"image {im_id}, object {gt_index}"


@dataclass(frozen=True)
class GroundTruth:
    """One annotated object instance: what ``scene_gt.json`` and ``scene_gt_info.json`` say of it."""

    scene_id: int
    im_id: int
    gt_index: int  # its place in the image's lists (and in its mask's file name)
    obj_id: int
    box: tuple[float, float, float, float]  # x, y, w, h px, of the kind asked for
    visib_fract: float
    gt_entry: Mapping[str, Any]  # its scene_gt.json entry, for a reader of the pose (cam_R_m2c, cam_t_m2c)
    gt_path: Path

    @property
    def where(self) -> str:
        """How error messages name it in ``gt_path``."""
        return _where(self.im_id, self.gt_index)


def scene_ground_truth(scene_dir: Path, box_kind: str, min_visib_fract: float,
                       obj_ids: Container[int] | None = None) -> Iterator[tuple[int, list[GroundTruth]]]:
    """Each image of the scene's ``scene_gt.json`` in id order, with its instances of ``obj_ids`` (all when None)
    that are at least ``min_visib_fract`` visible and have a box of ``box_kind`` with an area (maybe none).

    The one walk of the ground truth, so training, evaluation and ``popcode run --gt-boxes`` select the same
    instances and refuse the same malformed files.
    """
    gt_path, info_path = scene_dir / "scene_gt.json", scene_dir / "scene_gt_info.json"
    scene_gt, scene_info = int_keys(read_json(gt_path), gt_path), int_keys(read_json(info_path), info_path)
    for im_id, gts in sorted(scene_gt.items()):
        if im_id not in scene_info:
            raise PopcodeError(f"{info_path}: key '{im_id}' missing (it is in {gt_path.name})")
        infos = scene_info[im_id]
        if not isinstance(gts, list) or not isinstance(infos, list) or len(gts) != len(infos):
            raise PopcodeError(f"{gt_path} and {info_path.name}: image {im_id} must list the same number of objects")
        selected = []
        for gt_index, (gt, info) in enumerate(zip(gts, infos, strict=True)):
            where = _where(im_id, gt_index)
            obj_id = bop_id(gt, "obj_id", gt_path, where)
            if obj_ids is not None and obj_id not in obj_ids:
                continue
            visib_fract = float(json_field(info, "visib_fract", info_path, where, size=1)[0])
            x, y, w, h = json_field(info, box_kind, info_path, where, size=4)
            if visib_fract < min_visib_fract or w <= 0 or h <= 0:
                continue
            selected.append(GroundTruth(int(scene_dir.name), im_id, gt_index, obj_id,
                                        (float(x), float(y), float(w), float(h)), visib_fract, gt, gt_path))
        yield im_id, selected
