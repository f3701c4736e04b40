"""Trained models behind one call for evaluation: model files -> methods (table rows) -> rotations of split instances.

A ``.pt`` checkpoint runs through torch with the runtime's crop and decoding, an
``.onnx`` file through the shipped runtime. Several model files may form one
method: a method trained per object group is a model per group, and each
instance is routed to the model that knows its object.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from tqdm import tqdm

from popcode_runtime.crop import box_centre, crop_batch, read_image
from popcode_runtime.decoding import DECODERS, decode_output
from popcode_runtime.errors import PopcodeError
from popcode_runtime.estimator import PoseEstimator
from popcode_runtime.metadata import RotationFrame
from popcode_runtime.rotations import allocentric_to_egocentric

from ..data.bop import Instance
from ..model_io import load_checkpoint_model
from .split import rows_by_image
from .translation import object_points


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
    by_image = rows_by_image(instances)
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

