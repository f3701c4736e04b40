"""Per-instance errors and scores of rotations (or 6-D poses) on an evaluation split, for any number of methods.

What a split needs for scoring (object meshes, image sizes, depth images, a depth
renderer) is built once and shared by every method; VSD reads each depth image
when it is scored, so a large split never sits in memory.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.symmetries import symmetry_rotations

from ...data.bop import Instance, model_path
from ...data.box_noise import IOU_BINS, iou_bin_label
from ...data.gl import DepthRenderer
from ...data.meshes import load_mesh
from ...data.near_symmetry import look_alike_rotations
from ...data.symmetry_check import check_object_symmetries
from ...metrics.pose_errors import RenderDepth
from ...metrics.recall import (
    InstanceErrors,
    Thresholds,
    ambiguous_objects,
    binned_scores,
    group_scores,
    scores_per_object,
    tightest_recalls,
    visibility_scores,
)
from .detector_boxes import image_size_px
from .instance_errors import ObjectModel, compute_instance_errors
from .split import EvalSplit


def read_depth_mm(instance: Instance) -> np.ndarray:
    """The instance's test depth image in mm (0 = no measurement)."""
    if instance.depth_path is None:
        raise PopcodeError(f"{instance.image_path}: no depth image")
    depth = cv2.imread(str(instance.depth_path), cv2.IMREAD_ANYDEPTH)
    if depth is None:
        raise PopcodeError(f"cannot read depth image {instance.depth_path}")
    return depth.astype(np.float32) * np.float32(instance.depth_scale)


class SplitMetrics:
    """Object models, depth images and depth renderers of a split: built once, used by every method.

    ``vsd``: True requires depth (an error without it), None uses it when the
    split has it (a warning otherwise), False skips VSD, e_VSD<0.3 and VSS.
    """

    def __init__(self, split: EvalSplit, thresholds: Thresholds | None = None, vsd: bool | None = None) -> None:
        self.split, self.thresholds = split, thresholds or Thresholds()
        self._meshes = {obj_id: load_mesh(model_path(split.models_dir, obj_id)) for obj_id in split.obj_ids}
        self.objects = {obj_id: ObjectModel.from_info(np.asarray(mesh.vertices), split.models_info[obj_id])
                        for obj_id, mesh in self._meshes.items()}
        self.diameters_mm = {obj_id: model.diameter_mm for obj_id, model in self.objects.items()}
        self.look_alikes = self._look_alike_poses()
        self.ambiguous = ambiguous_objects(split.models_info)
        self._renderer: Any = None
        self._renderer_key: tuple[int, int, int] | None = None
        self.use_depth = False
        without_depth = [inst for inst in split.instances if inst.depth_path is None]
        if vsd and without_depth:
            raise PopcodeError(f"VSD needs depth images, but {len(without_depth)} of {len(split.instances)} "
                               f"instances have none (e.g. {without_depth[0].image_path}); pass --no-vsd")
        if vsd is None and without_depth:
            warnings.warn(f"{len(without_depth)} instances have no depth image: VSD, e_VSD<0.3 and VSS are skipped",
                          stacklevel=2)
        elif vsd is not False:
            self.use_depth = True
        self.image_size_px = _image_sizes_px(split.instances)

    def _render_depth(self, obj_id: int, K: np.ndarray, width: int, height: int) -> RenderDepth:
        """Depth of the object in a pose; one OpenGL context per (object, image size), kept while in use.

        Only one lives at a time: pyrender's EGL contexts share one display, and
        closing any of them ends the others.
        """
        key = (obj_id, width, height)
        if self._renderer_key != key:
            self.close()
            mesh = self._meshes[obj_id]
            self._renderer, self._renderer_key = DepthRenderer(mesh.vertices, mesh.faces, width, height), key
        renderer = self._renderer
        return lambda R, t: renderer.render(K, R, t)

    def _look_alike_poses(self) -> dict[int, np.ndarray]:
        """Object -> its symmetric and look-alike poses ``(K, 3, 3)``, for the parts that nearly have a symmetry
        they do not declare. A part whose declared symmetries fail the check is scored as before, with a warning."""
        poses = {}
        for obj_id, mesh in self._meshes.items():
            info = self.split.models_info[obj_id]
            try:
                found = check_object_symmetries(model_path(self.split.models_dir, obj_id), info, obj_id, mesh)
            except PopcodeError as error:
                warnings.warn(f"{error} (scored as declared; no re_look_alike_deg for it)", stacklevel=3)
                continue
            if found:
                poses[obj_id] = look_alike_rotations(found, symmetry_rotations(info))
        return poses

    def errors(self, R_est: np.ndarray, t_est_mm: np.ndarray | None = None, depth: bool = True,
               rows: np.ndarray | None = None) -> InstanceErrors:
        """Every metric's error of the estimates ``(N, 3, 3)``, one per split instance, in split order.

        ``t_est_mm (N, 3)`` scores full 6-D poses; without it every estimate gets
        the ground-truth translation (the paper's protocol). ``depth=False`` skips
        the depth-based errors even where the split has depth (a quick score of
        many candidate rotations, e.g. each hypothesis rank). ``rows (N,)`` names
        the split instance each estimate is scored against instead (repeats
        allowed: a results file's estimates against every instance they may
        match). Estimates are scored in groups of one object and image size, so
        each group renders its depth with one renderer.
        """
        instances = self.split.instances
        rows = np.arange(len(instances)) if rows is None else np.asarray(rows, dtype=int)
        if np.shape(R_est) != (len(rows), 3, 3):
            raise PopcodeError(f"predictions have shape {np.shape(R_est)}; the split has {len(rows)} "
                               "instances, so (N, 3, 3) with N = that count is needed")
        if t_est_mm is not None and np.shape(t_est_mm) != (len(rows), 3):
            raise PopcodeError(f"translations have shape {np.shape(t_est_mm)}; (N, 3) with N = "
                               f"{len(rows)} is needed")
        if not np.isfinite(R_est).all() or (t_est_mm is not None and not np.isfinite(t_est_mm).all()):
            raise PopcodeError("predictions contain NaN or inf")
        keys = [(instances[row].obj_id, *map(int, self.image_size_px[row])) for row in rows]
        parts = []
        for key in sorted(set(keys)):
            chosen = np.array([i for i, k in enumerate(keys) if k == key])
            t_chosen = None if t_est_mm is None else np.asarray(t_est_mm, np.float64)[chosen]
            parts.append((chosen, self._group_errors(rows[chosen], np.asarray(R_est, np.float64)[chosen], t_chosen,
                                                     depth)))
        return _merge_rows(len(rows), parts)

    def scores(self, errors: InstanceErrors) -> tuple[dict[int, dict[str, float]], dict[str, dict[str, float]]]:
        """Scores per object and per ambiguity group (the paper's Tables III and IV)."""
        return (scores_per_object(errors, self.diameters_mm, self.thresholds),
                group_scores(errors, self.diameters_mm, self.ambiguous, self.thresholds))

    def by_visibility(self, errors: InstanceErrors) -> dict[str, dict[str, float]]:
        """Scores per ``visib_fract`` bin (``recall.VISIBILITY_BINS``), each with its instance count."""
        visib_fract = np.array([inst.visib_fract for inst in self.split.instances])
        return visibility_scores(errors, visib_fract, self.diameters_mm, self.thresholds)

    def by_box_iou(self, errors: InstanceErrors) -> dict[str, dict[str, float]]:
        """Scores per bin of the box's IoU with the truth (``box_noise.IOU_BINS``), each with its instance count;
        empty while the split has its ground-truth boxes."""
        boxes = self.split.detector_boxes
        if boxes is None:
            return {}
        bins = [(iou_bin_label(low, high), low, high) for low, high in IOU_BINS]
        return binned_scores(errors, boxes.iou, bins, self.diameters_mm, self.thresholds, "box IoUs")

    def tightest(self, errors: InstanceErrors) -> dict[str, dict[str, float]]:
        """Recall at each metric's tightest threshold alone, per ambiguity group."""
        return group_scores(errors, self.diameters_mm, self.ambiguous, self.thresholds, score=tightest_recalls)

    def _group_errors(self, rows: np.ndarray, R_est: np.ndarray, t_est_mm: np.ndarray | None,
                      use_depth: bool = True) -> InstanceErrors:
        chosen = [self.split.instances[i] for i in rows]
        depth = _DepthImages(chosen) if self.use_depth and use_depth else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the skipped-VSD warning was given once, in __init__
            return compute_instance_errors(
                np.array([inst.obj_id for inst in chosen]), R_est, np.stack([inst.R_m2c for inst in chosen]),
                np.stack([inst.t_m2c_mm for inst in chosen]), np.stack([inst.K for inst in chosen]),
                self.image_size_px[rows, 0], self.objects, self.thresholds, depth,
                self._render_depth if depth is not None else None, t_est_mm,
            )

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        self._renderer, self._renderer_key = None, None


def _merge_rows(count: int, parts: Sequence[tuple[np.ndarray, InstanceErrors]]) -> InstanceErrors:
    """One :class:`InstanceErrors` of ``count`` instances from parts that hold the given rows."""
    merged: dict[str, np.ndarray | None] = {}
    for name, first in parts[0][1].__dict__.items():
        if first is None:
            merged[name] = None
            continue
        merged[name] = np.empty((count, *np.shape(first)[1:]), dtype=np.asarray(first).dtype)
        for rows, part in parts:
            merged[name][rows] = getattr(part, name)
    return InstanceErrors(**merged)


def _image_sizes_px(instances: Sequence[Instance]) -> np.ndarray:
    """Width and height ``(N, 2)`` of each instance's image (MSPD thresholds scale with the width)."""
    sizes: dict[Path, tuple[int, int]] = {}
    for inst in instances:
        if inst.image_path not in sizes:
            sizes[inst.image_path] = image_size_px(inst.image_path)
    return np.array([sizes[inst.image_path] for inst in instances], dtype=np.float64)


class _DepthImages(Sequence[np.ndarray]):
    """The instances' test depth images [mm], read when indexed: a large split never sits in memory."""

    def __init__(self, instances: Sequence[Instance]) -> None:
        self._instances = instances

    def __len__(self) -> int:
        return len(self._instances)

    def __getitem__(self, index: int) -> np.ndarray:
        return read_depth_mm(self._instances[index])
