"""Models (checkpoints or ONNX files) + a BOP split -> per-instance errors and the paper's tables.

Rotation from the model, translation from the ground truth (the paper's
protocol); optionally also full 6-D poses, with the translation fitted to the
box as the runtime does it (:mod:`.translation`). Several model files may form one method (one row of a table): a
method trained per object group is a model per group, and each instance is
routed to the model that knows its object. Object meshes and depth renderers
are built once per split and shared by every method.
"""

from __future__ import annotations

import time
import warnings
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np
import torch
from tqdm import tqdm

from popcode_runtime.crop import box_centre, crop_batch, read_image
from popcode_runtime.decoding import DECODERS, decode_output
from popcode_runtime.errors import PopcodeError
from popcode_runtime.estimator import PoseEstimator
from popcode_runtime.metadata import RotationFrame
from popcode_runtime.rotations import allocentric_to_egocentric

from ..data.bop import Instance, model_path, read_bop_split
from ..export import load_checkpoint_model
from .instance_errors import ObjectModel, compute_instance_errors
from .pose_error import RenderDepth
from .scores import InstanceErrors, Thresholds, scores_per_object, tightest_recalls
from .tables import ambiguous_objects, group_scores
from .translation import object_points, translations_from_boxes

EVAL_MIN_VISIB_FRACT = 0.1  # the BOP19 test targets: at least 10 % of the object visible


@dataclass(frozen=True)
class EvalSplit:
    """The ground-truth instances to evaluate and the objects they show."""

    instances: list[Instance]
    models_info: dict[int, dict[str, Any]]
    models_dir: Path

    @property
    def obj_ids(self) -> list[int]:
        return sorted({inst.obj_id for inst in self.instances})


def read_eval_split(split_dirs: Sequence[str | Path], models_dir: str | Path, obj_ids: Iterable[int] | None = None,
                    max_instances: int | None = None, min_visib_fract: float = EVAL_MIN_VISIB_FRACT) -> EvalSplit:
    """Instances of one or more BOP splits; ``max_instances`` keeps the first N of each object."""
    if not split_dirs:
        raise PopcodeError("give at least one split folder")
    instances: list[Instance] = []
    models_info: dict[int, dict[str, Any]] = {}
    for split_dir in split_dirs:
        split = read_bop_split(split_dir, models_dir, obj_ids=obj_ids, min_visib_fract=min_visib_fract)
        instances += split.instances
        models_info = split.models_info
    if max_instances is not None:
        if max_instances < 1:
            raise PopcodeError(f"max_instances must be at least 1, got {max_instances}")
        taken: dict[int, int] = defaultdict(int)
        kept = []
        for inst in instances:
            if taken[inst.obj_id] < max_instances:
                taken[inst.obj_id] += 1
                kept.append(inst)
        instances = kept
    used = {inst.obj_id for inst in instances}
    return EvalSplit(instances, {k: v for k, v in models_info.items() if k in used}, Path(models_dir))


class RotationModel(Protocol):
    """A trained model behind one call: the boxes of one image -> model-to-camera rotations."""

    path: Path
    obj_ids: frozenset[int]
    objects: Mapping[int, Mapping[str, Any]]  # the model's metadata entries: symmetries, extents, hull points

    def predict(self, image: np.ndarray, boxes: list[tuple[float, ...]], K: np.ndarray,
                obj_ids: list[int]) -> np.ndarray:
        """Rotations ``(n, 3, 3)`` in the camera frame."""
        ...


class OnnxModel:
    """An ONNX file run through the shipped runtime, so the runtime is what gets evaluated."""

    def __init__(self, path: str | Path, decoder: str = "argmax") -> None:
        self.path = Path(path)
        self.estimator = PoseEstimator(self.path, decoder=decoder)
        self.objects = self.estimator.metadata.objects
        self.obj_ids = frozenset(self.objects)

    def predict(self, image: np.ndarray, boxes: list[tuple[float, ...]], K: np.ndarray,
                obj_ids: list[int]) -> np.ndarray:
        predictions = self.estimator.predict(image, boxes, K=K, obj_ids=obj_ids)
        return np.stack([p.R_m2c for p in predictions])


class CheckpointModel:
    """A training checkpoint run through torch, with the runtime's crop and decoding."""

    def __init__(self, path: str | Path, decoder: str = "argmax") -> None:
        if decoder not in DECODERS:
            raise PopcodeError(f"unknown decoder {decoder!r}; expected one of {DECODERS}")
        self.path, self.decoder = Path(path), decoder
        self.network, self.metadata = load_checkpoint_model(self.path)
        self.objects = self.metadata.objects
        self.obj_ids = frozenset(self.objects)

    def predict(self, image: np.ndarray, boxes: list[tuple[float, ...]], K: np.ndarray,
                obj_ids: list[int]) -> np.ndarray:
        crops = crop_batch(image, boxes, self.metadata.input_size, self.metadata.crop_padding)
        with torch.no_grad():
            output = self.network(torch.from_numpy(crops)).numpy()
        R = decode_output(output, self.metadata, self.decoder).R
        if self.metadata.rotation_frame == RotationFrame.ALLOCENTRIC:
            R = allocentric_to_egocentric(R, K, np.stack([box_centre(box) for box in boxes]))
        return R


def load_model(path: str | Path, decoder: str = "argmax") -> RotationModel:
    """A ``.pt`` checkpoint or an ``.onnx`` model, by file suffix."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"model file not found: {path}")
    if path.suffix == ".onnx":
        return OnnxModel(path, decoder)
    if path.suffix == ".pt":
        return CheckpointModel(path, decoder)
    raise PopcodeError(f"{path}: a model is a training checkpoint (.pt) or an ONNX file (.onnx)")


@dataclass(frozen=True)
class Method:
    """One row of the tables: a name and the models that together cover its objects."""

    name: str
    models: tuple[RotationModel, ...]

    def model_of(self) -> dict[int, RotationModel]:
        """Object id -> the one model that estimates it; two models for one object is an error."""
        owner: dict[int, RotationModel] = {}
        for model in self.models:
            for obj_id in model.obj_ids:
                if obj_id in owner:
                    raise PopcodeError(f"method {self.name!r}: object {obj_id} is in both {owner[obj_id].path} "
                                       f"and {model.path}")
                owner[obj_id] = model
        return owner

    def object_points(self) -> dict[int, np.ndarray]:
        """Object id -> the points its model's metadata gives the runtime to fit a box."""
        return {obj_id: points for model in self.models for obj_id, points in object_points(model.objects).items()}


def predict_rotations(method: Method, instances: Sequence[Instance], progress: bool = True,
                      ) -> tuple[np.ndarray, float]:
    """Rotations ``(N, 3, 3)`` for the instances and the model's seconds per crop.

    Each image is read once; the model time covers crop, network and decoding.
    """
    owner = method.model_of()
    missing = sorted({inst.obj_id for inst in instances} - set(owner))
    if missing:
        raise PopcodeError(f"method {method.name!r} has no model for objects {missing} of the split "
                           f"(its models know {sorted(owner)}); pass --obj-ids to evaluate fewer objects")
    by_image: dict[Path, list[int]] = defaultdict(list)
    for index, inst in enumerate(instances):
        by_image[inst.image_path].append(index)
    R_est = np.empty((len(instances), 3, 3))
    model_s = 0.0
    for image_path, rows in tqdm(by_image.items(), desc=f"predict {method.name}", unit="img", disable=not progress):
        image = read_image(image_path)
        for model in method.models:
            chosen = [i for i in rows if instances[i].obj_id in model.obj_ids]
            if not chosen:
                continue
            started = time.perf_counter()
            R_est[chosen] = model.predict(image, [instances[i].box for i in chosen], instances[chosen[0]].K,
                                          [instances[i].obj_id for i in chosen])
            model_s += time.perf_counter() - started
    return R_est, model_s / max(len(instances), 1)


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
        from ..data.render import load_mesh  # pyrender/EGL, loaded only when evaluating

        self.split, self.thresholds = split, thresholds or Thresholds()
        self._meshes = {obj_id: load_mesh(model_path(split.models_dir, obj_id)) for obj_id in split.obj_ids}
        self.objects = {obj_id: ObjectModel.from_info(np.asarray(mesh.vertices), split.models_info[obj_id])
                        for obj_id, mesh in self._meshes.items()}
        self.diameters_mm = {obj_id: model.diameter_mm for obj_id, model in self.objects.items()}
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
        from ..data.render import DepthRenderer

        key = (obj_id, width, height)
        if self._renderer_key != key:
            self.close()
            mesh = self._meshes[obj_id]
            self._renderer, self._renderer_key = DepthRenderer(mesh.vertices, mesh.faces, width, height), key
        renderer = self._renderer
        return lambda R, t: renderer.render(K, R, t)

    def errors(self, R_est: np.ndarray, t_est_mm: np.ndarray | None = None) -> InstanceErrors:
        """Every metric's error of the estimates ``(N, 3, 3)``, one per split instance, in split order.

        ``t_est_mm (N, 3)`` scores full 6-D poses; without it every estimate gets
        the ground-truth translation (the paper's protocol). Instances are scored
        in groups of one object and image size, so each group renders its depth
        with one renderer.
        """
        instances = self.split.instances
        if np.shape(R_est) != (len(instances), 3, 3):
            raise PopcodeError(f"predictions have shape {np.shape(R_est)}; the split has {len(instances)} "
                               "instances, so (N, 3, 3) with N = that count is needed")
        if t_est_mm is not None and np.shape(t_est_mm) != (len(instances), 3):
            raise PopcodeError(f"translations have shape {np.shape(t_est_mm)}; (N, 3) with N = "
                               f"{len(instances)} is needed")
        if not np.isfinite(R_est).all() or (t_est_mm is not None and not np.isfinite(t_est_mm).all()):
            raise PopcodeError("predictions contain NaN or inf")
        keys = [(inst.obj_id, *map(int, size)) for inst, size in zip(instances, self.image_size_px, strict=True)]
        parts = []
        for key in sorted(set(keys)):
            rows = np.array([i for i, k in enumerate(keys) if k == key])
            t_rows = None if t_est_mm is None else np.asarray(t_est_mm, np.float64)[rows]
            parts.append((rows, self._group_errors(rows, np.asarray(R_est, np.float64)[rows], t_rows)))
        return _merge_rows(len(instances), parts)

    def scores(self, errors: InstanceErrors) -> tuple[dict[int, dict[str, float]], dict[str, dict[str, float]]]:
        """Scores per object and per ambiguity group (the paper's Tables III and IV)."""
        return (scores_per_object(errors, self.diameters_mm, self.thresholds),
                group_scores(errors, self.diameters_mm, self.ambiguous, self.thresholds))

    def tightest(self, errors: InstanceErrors) -> dict[str, dict[str, float]]:
        """Recall at each metric's tightest threshold alone, per ambiguity group."""
        return group_scores(errors, self.diameters_mm, self.ambiguous, self.thresholds, score=tightest_recalls)

    def _group_errors(self, rows: np.ndarray, R_est: np.ndarray, t_est_mm: np.ndarray | None) -> InstanceErrors:
        chosen = [self.split.instances[i] for i in rows]
        depth = _DepthImages(chosen) if self.use_depth else None
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
            height, width = read_image(inst.image_path).shape[:2]
            sizes[inst.image_path] = (width, height)
    return np.array([sizes[inst.image_path] for inst in instances], dtype=np.float64)


class _DepthImages(Sequence[np.ndarray]):
    """The instances' test depth images [mm], read when indexed: a large split never sits in memory."""

    def __init__(self, instances: Sequence[Instance]) -> None:
        self._instances = instances

    def __len__(self) -> int:
        return len(self._instances)

    def __getitem__(self, index: int) -> np.ndarray:
        return read_depth_mm(self._instances[index])


@dataclass(frozen=True)
class FullPose:
    """Full 6-D poses of one method: its rotations with the translation fitted to each instance's box."""

    t_est_mm: np.ndarray  # (N, 3) from the method's rotation, split order
    t_gt_rotation_mm: np.ndarray  # (N, 3) from the ground-truth rotation: the error of the box fit alone
    errors: InstanceErrors  # of (R_est, t_est_mm)
    per_object: dict[int, dict[str, float]]
    groups: dict[str, dict[str, float]]


def full_pose(R_est: np.ndarray, metrics: SplitMetrics, points_mm: Mapping[int, np.ndarray]) -> FullPose:
    """Fit each instance's translation to its box (with ``R_est`` and with the truth) and score the 6-D poses."""
    instances = metrics.split.instances
    t_est_mm = translations_from_boxes(R_est, instances, points_mm)
    t_gt_rotation_mm = translations_from_boxes(np.stack([inst.R_m2c for inst in instances]), instances, points_mm)
    errors = metrics.errors(R_est, t_est_mm)
    return FullPose(t_est_mm, t_gt_rotation_mm, errors, *metrics.scores(errors))


@dataclass(frozen=True)
class MethodResult:
    """What one method scored on the split; scores are fractions in [0, 1]."""

    name: str
    split: EvalSplit  # the instances scored, in the order of every per-instance array
    model_paths: tuple[str, ...]
    R_est: np.ndarray  # (N, 3, 3), split order
    errors: InstanceErrors
    per_object: dict[int, dict[str, float]]
    groups: dict[str, dict[str, float]]
    tightest: dict[str, dict[str, float]]  # per group, the recall at each metric's tightest threshold
    model_ms_per_crop: float  # crop + network + decoding; NaN for given rotations
    metric_s: float
    full_pose: FullPose | None = None  # when asked for: translation from the box, 6-D scores
    thresholds: Thresholds = field(default_factory=Thresholds)  # those every score was computed with


def evaluate_rotations(name: str, R_est: np.ndarray, metrics: SplitMetrics, model_paths: tuple[str, ...] = (),
                       model_ms_per_crop: float = float("nan"),
                       points_mm: Mapping[int, np.ndarray] | None = None) -> MethodResult:
    """Score given rotations (one per split instance): the path for precomputed estimates.

    With ``points_mm`` (object id -> points the runtime fits to a box) full 6-D
    poses are scored too, the translation fitted to each instance's box.
    """
    started = time.perf_counter()
    R_est = np.asarray(R_est, np.float64)
    errors = metrics.errors(R_est)
    per_object, groups = metrics.scores(errors)
    pose = None if points_mm is None else full_pose(R_est, metrics, points_mm)
    return MethodResult(name, metrics.split, model_paths, R_est, errors, per_object, groups, metrics.tightest(errors),
                        model_ms_per_crop, time.perf_counter() - started, pose, metrics.thresholds)


def evaluate_model(method: Method, metrics: SplitMetrics, progress: bool = True,
                   translation: bool = False) -> MethodResult:
    """Predict every instance of the split with the method's models, then score (6-D too with ``translation``)."""
    R_est, model_s_per_crop = predict_rotations(method, metrics.split.instances, progress)
    return evaluate_rotations(method.name, R_est, metrics, tuple(str(m.path) for m in method.models),
                              1000.0 * model_s_per_crop, method.object_points() if translation else None)


def methods_from_paths(paths: Sequence[str | Path], names: Sequence[str] | None = None,
                       decoder: str = "argmax") -> list[Method]:
    """Methods from model files; models given the same name form one method (one table row).

    Without names each file is its own method, named after the file.
    """
    if names and len(names) != len(paths):
        raise PopcodeError(f"{len(names)} names for {len(paths)} models: give one --name per model, or none")
    grouped: dict[str, list[RotationModel]] = {}
    for index, path in enumerate(paths):
        name = names[index] if names else Path(path).stem
        grouped.setdefault(name, []).append(load_model(path, decoder))
    return [Method(name, tuple(models)) for name, models in grouped.items()]


def restrict_to_objects(split: EvalSplit, obj_ids: Iterable[int]) -> EvalSplit:
    """The split's instances of ``obj_ids`` only."""
    wanted = set(obj_ids)
    kept = [inst for inst in split.instances if inst.obj_id in wanted]
    return EvalSplit(kept, {k: v for k, v in split.models_info.items() if k in wanted}, split.models_dir)


def _shared_split(methods: Sequence[Method], split: EvalSplit, obj_ids: Iterable[int] | None) -> EvalSplit:
    """The instances every method can estimate, so that all rows of a table score the same instances.

    With ``obj_ids`` every method must know each of them; without, objects some
    method lacks are left out with a warning.
    """
    known = [set(method.model_of()) for method in methods]
    if obj_ids is not None:
        wanted = set(obj_ids)
        for method, objects in zip(methods, known, strict=True):
            lacking = sorted(wanted - objects)
            if lacking:
                raise PopcodeError(f"method {method.name!r} has no model for objects {lacking} "
                                   f"(its models know {sorted(objects)})")
    shared = set.intersection(*known) & set(split.obj_ids)
    if not shared:
        raise PopcodeError(f"no object of the split ({split.obj_ids}) is known to every model: "
                           + "; ".join(f"{m.name!r} knows {sorted(o)}" for m, o in zip(methods, known, strict=True)))
    left_out = sorted(set(split.obj_ids) - shared)
    if left_out:
        warnings.warn(f"objects {left_out} of the split are not known to every model and are not evaluated",
                      stacklevel=3)
    return restrict_to_objects(split, shared)


def evaluate_models(methods: Sequence[Method], split: EvalSplit, thresholds: Thresholds | None = None,
                    vsd: bool | None = None, obj_ids: Iterable[int] | None = None,
                    progress: bool = True, translation: bool = False) -> list[MethodResult]:
    """Every method on the same split instances, sharing object models and depth renderers.

    ``translation`` also fits each instance's translation to its box, as the
    runtime does, and scores the full 6-D poses (:class:`FullPose`).
    """
    if not methods:
        raise PopcodeError("no models to evaluate")
    metrics = SplitMetrics(_shared_split(methods, split, obj_ids), thresholds, vsd)
    try:
        return [evaluate_model(method, metrics, progress, translation) for method in methods]
    finally:
        metrics.close()
