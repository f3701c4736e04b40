"""Reader for BOP-format splits: the one way data enters training (docs/design.md#bop-files).

Only the JSON files are read when a split is indexed; images are opened by whoever uses an
:class:`Instance`. Works on T-LESS as published (``gray/`` or ``rgb/``, png/jpg/tif) and on what
:mod:`popcode_trainer.data.render` writes.
"""

from __future__ import annotations

import numbers
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.checks import shown
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json, require_folder
from popcode_runtime.base.image_size import image_size
from popcode_runtime.base.limits import MAX_OBJECTS
from popcode_runtime.bop.split import (
    BOX_KINDS,
    GroundTruth,
    folder_index,
    image_folder,
    int_keys,
    json_field,
    read_cam_K,
    read_depth_scale,
    scene_folders,
    scene_ground_truth,
)
from popcode_runtime.geometry.crop import check_box
from popcode_runtime.model.metadata import check_object_info

from .meshes import load_mesh
from .objects import mesh_diameter_mm

RENDER_MARKER = "popcode_render.json"  # written by the renderer into a split it made


@dataclass(frozen=True)
class Instance:
    """One annotated object in one image, in BOP conventions (object-to-camera, mm, OpenCV camera)."""

    image_path: Path
    obj_id: int
    box: tuple[float, float, float, float]  # x, y, w, h px
    K: np.ndarray  # (3, 3)
    R_m2c: np.ndarray  # (3, 3)
    t_m2c_mm: np.ndarray  # (3,)
    scene_id: int
    im_id: int
    gt_index: int
    visib_fract: float
    rendered: bool  # synthetic image: gets the brightness and background augmentation
    depth_path: Path | None
    mask_visib_path: Path | None
    depth_scale: float  # depth png value times this is mm
    cluttered: bool = False  # from a scene split: the image around the object is the scene's own clutter


@dataclass(frozen=True)
class BopSplit:
    """The selected instances of a split and the models they refer to."""

    instances: list[Instance]
    models_info: dict[int, dict[str, Any]]
    split_dir: Path
    models_dir: Path

    def model_path(self, obj_id: int) -> Path:
        """Path of the object's mesh (``obj_XXXXXX.ply``)."""
        return model_path(self.models_dir, obj_id)


def model_path(models_dir: str | Path, obj_id: int) -> Path:
    path = Path(models_dir) / f"obj_{obj_id:06d}.ply"
    if not path.is_file():
        raise PopcodeError(f"model file not found: {path}")
    return path


def _rotation(values: np.ndarray, path: Path, where: str) -> np.ndarray:
    """A row-major ``cam_R_m2c`` as a 3x3 rotation; a scaled, skewed or mirrored matrix is corrupt ground truth."""
    R = values.reshape(3, 3)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) <= 0:
        deviation = np.abs(R @ R.T - np.eye(3)).max()
        raise PopcodeError(f"{path}: key 'cam_R_m2c' in {where} is not a rotation matrix "
                           f"(R R^T deviates from I by {deviation:.3g}, det {np.linalg.det(R):.3g})")
    return R


def gt_rotation(gt: GroundTruth) -> np.ndarray:
    """An annotated instance's ``cam_R_m2c`` (3x3), refused in one line where it is missing or not a rotation."""
    return _rotation(json_field(gt.gt_entry, "cam_R_m2c", gt.gt_path, gt.where, size=9), gt.gt_path, gt.where)


def check_image_matches(instance: Instance, width: int, height: int) -> None:
    """Refuse an image whose size contradicts its annotations: the box or K's principal point outside it.

    Called when a split is read, with the size in each image's header, and where
    an image is decoded (the crop); a split with resized or swapped images would
    otherwise train on the wrong pixels without a word.
    """
    x, y, w, h = instance.box
    where = f"scene {instance.scene_id}, image {instance.im_id}, object {instance.gt_index}"
    if x >= width or y >= height or x + w <= 0 or y + h <= 0:
        raise PopcodeError(f"{instance.image_path} is {width}x{height} px but the box {list(instance.box)} of {where} "
                           "(scene_gt_info.json) lies outside it: the images do not match the annotations")
    try:
        check_box(instance.box, (height, width))  # the runtime's bounds: a huge box would allocate without bound
    except PopcodeError as error:
        raise PopcodeError(f"{instance.image_path}, {where} (scene_gt_info.json): {error}") from error
    cx, cy = instance.K[0, 2], instance.K[1, 2]
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise PopcodeError(f"{instance.image_path} is {width}x{height} px but cam_K of image {instance.im_id} "
                           f"(scene_camera.json) puts the principal point at ({cx:g}, {cy:g}), outside it: "
                           "the images do not match the camera")


def check_against_headers(instances: Sequence[Instance]) -> None:
    """Every instance against the size its image's header gives (:func:`check_image_matches`), before any image is
    decoded: a split whose images contradict their annotations is refused before a progress bar opens, not at the
    crop that meets it. An image whose header is not read here (a FIFO, an unknown format) is checked when it is
    decoded."""
    sizes: dict[Path, tuple[int, int] | None] = {}
    for instance in instances:
        path = Path(instance.image_path)
        if path not in sizes:
            try:  # a FIFO would block the open
                sizes[path] = image_size(path) if path.is_file() else None
            except OSError:
                sizes[path] = None
        if sizes[path] is not None:
            check_image_matches(instance, *sizes[path])


def load_models_info(models_dir: str | Path) -> dict[int, dict[str, Any]]:
    """``models_info.json`` keyed by object id, each entry checked as the runtime checks a model's objects (numbers
    that are numbers, symmetries counted before they are read) and with a positive diameter.

    The object count is checked before any entry, against the runtime's limit: what trains here must load there.
    """
    path = Path(models_dir) / "models_info.json"
    models_info = int_keys(read_json(path), path)
    if len(models_info) > MAX_OBJECTS:
        raise PopcodeError(f"{path} lists {len(models_info)} objects; at most {MAX_OBJECTS} are allowed (the "
                           "runtime's limit per model): split them into several models folders")
    for obj_id, info in models_info.items():
        diameter = json_field(info, "diameter", path, f"object {obj_id}")
        if isinstance(diameter, bool) or not isinstance(diameter, numbers.Real) or not diameter > 0:
            raise PopcodeError(f"{path}: key 'diameter' of object {obj_id} must be a positive number, got "
                               f"{shown(diameter)} ({type(diameter).__name__}){_measured(models_dir, obj_id)}")
        try:
            check_object_info(obj_id, info)
        except PopcodeError as error:
            raise PopcodeError(f"{path}: {error}") from error
    return models_info


def _measured(models_dir: str | Path, obj_id: int) -> str:
    """What a refused diameter should be: the mesh's, where it has one that loads (an error message's tail)."""
    try:
        mesh = load_mesh(model_path(models_dir, obj_id))
    except PopcodeError:
        return ""
    return (f"; its mesh's diameter is {mesh_diameter_mm(mesh):.6g} mm (the largest distance between two of its "
            "vertices: popcode_trainer.data.objects.model_info writes it)")


def _scene_instances(scene_dir: Path, obj_ids: set[int], min_visib_fract: float, box: str,
                     rendered: bool, cluttered: bool) -> Iterable[Instance]:
    camera_path = scene_dir / "scene_camera.json"
    scene_camera = int_keys(read_json(camera_path), camera_path)
    images_dir = image_folder(scene_dir)
    images, depths = folder_index(images_dir), folder_index(scene_dir / "depth")
    masks = folder_index(scene_dir / "mask_visib")
    for im_id, selected in scene_ground_truth(scene_dir, box, min_visib_fract, obj_ids):
        if im_id not in scene_camera:
            raise PopcodeError(f"{camera_path}: key '{im_id}' missing (it is in scene_gt.json)")
        camera = scene_camera[im_id]
        K = read_cam_K(camera, camera_path, im_id)
        depth_scale = read_depth_scale(camera, camera_path, im_id)
        stem = f"{im_id:06d}"
        for gt in selected:
            if stem not in images:
                raise PopcodeError(f"image {stem} listed in {gt.gt_path} is missing from {images_dir}")
            yield Instance(
                image_path=images[stem],
                obj_id=gt.obj_id,
                box=gt.box,
                K=K,
                R_m2c=gt_rotation(gt),
                t_m2c_mm=json_field(gt.gt_entry, "cam_t_m2c", gt.gt_path, gt.where, size=3),
                scene_id=gt.scene_id,
                im_id=im_id,
                gt_index=gt.gt_index,
                visib_fract=gt.visib_fract,
                rendered=rendered,
                depth_path=depths.get(stem),
                mask_visib_path=masks.get(f"{stem}_{gt.gt_index:06d}"),
                depth_scale=depth_scale,
                cluttered=cluttered,
            )


def is_rendered_split(split_dir: Path) -> bool:
    """Synthetic split: made by our renderer, or a BOP physically-based one (``train_pbr``)."""
    return (split_dir / RENDER_MARKER).is_file() or "pbr" in split_dir.name


def is_scene_split(split_dir: Path) -> bool:
    """Cluttered scenes: rendered with ``--scenes``, a BOP physically-based split, or real images (a BOP test
    or real training split shows its parts where they lie); only single-object renders are not."""
    marker = split_dir / RENDER_MARKER
    if marker.is_file():
        return "scenes" in read_json(marker)
    return True


def read_bop_split(
    split_dir: str | Path,
    models_dir: str | Path,
    obj_ids: Iterable[int] | None = None,
    min_visib_fract: float = 0.6,
    box: str = "bbox_obj",
    rendered: bool | None = None,
) -> BopSplit:
    """Index the instances of ``obj_ids`` (default: all in ``models_info.json``) with enough of them visible.

    ``box`` picks the BOP box (``bbox_obj`` or ``bbox_visib``); ``rendered`` overrides the guess
    from the split (see :func:`is_rendered_split`).
    """
    split_dir, models_dir = Path(split_dir), Path(models_dir)
    if box not in BOX_KINDS:
        raise PopcodeError(f"box must be one of {list(BOX_KINDS)}, got {box!r}")
    if not 0.0 <= min_visib_fract < float("inf"):  # NaN too: it compares False and would keep every instance
        raise PopcodeError(f"min_visib_fract must be a number >= 0, got {min_visib_fract}")
    scene_dirs = scene_folders(split_dir)
    require_folder(models_dir, "models folder")
    models_info = load_models_info(models_dir)
    wanted = set(models_info) if obj_ids is None else {int(obj_id) for obj_id in obj_ids}
    unknown = sorted(wanted - set(models_info))
    if unknown:
        raise PopcodeError(f"object ids {unknown} are not in {models_dir / 'models_info.json'} "
                           f"(it lists {sorted(models_info)})")
    if rendered is None:
        rendered = is_rendered_split(split_dir)
    cluttered = is_scene_split(split_dir)
    instances = [
        instance
        for scene_dir in scene_dirs
        for instance in _scene_instances(scene_dir, wanted, min_visib_fract, box, rendered, cluttered)
    ]
    if not instances:
        raise PopcodeError(f"no instances of objects {sorted(wanted)} with visib_fract >= {min_visib_fract} "
                           f"in {split_dir}")
    check_against_headers(instances)
    return BopSplit(instances=instances, models_info=models_info, split_dir=split_dir, models_dir=models_dir)
