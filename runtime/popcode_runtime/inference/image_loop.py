"""The one per-image loop: read each image once, route each box to the model of its object, predict per model.

``popcode run``, the trainer's evaluation and the confidence fit at export all
estimate many boxes on many images with one or more models, each model knowing
its own objects. They go through :func:`estimate_images`, so that an image is
read once, a model sees all of its boxes of an image in one
:meth:`PoseEstimator.predict` call, and an object known to two models is
refused the same way everywhere.
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from ..base.errors import PopcodeError
from ..depth.surface_fit import read_depth
from ..geometry.crop import read_image
from .estimator import PoseEstimator
from .prediction import Prediction

Key = TypeVar("Key")


@dataclass(frozen=True)
class ImageBoxes(Generic[Key]):
    """The boxes to estimate on one image; ``key`` is the caller's name for the image, handed back with the results."""

    key: Key
    path: Path
    K: np.ndarray | None  # the image's camera (3, 3); None where the models and options need none
    boxes: Sequence[tuple[float, float, float, float]]  # x, y, w, h px
    obj_ids: Sequence[int]  # the object in each box
    depth_path: Path | None = None  # the image's depth image, read and given to the models when set
    depth_scale: float | None = 1.0  # mm per depth unit; None (its split lacks one) only without depth_path

    def __post_init__(self) -> None:
        if len(self.obj_ids) != len(self.boxes):
            raise PopcodeError(f"{self.path}: {len(self.obj_ids)} object ids for {len(self.boxes)} boxes")


@dataclass(frozen=True)
class ImageEstimates(Generic[Key]):
    """The estimates of one image's boxes."""

    key: Key
    image: np.ndarray  # as read, for drawing the estimates on it
    predictions: list[Prediction]  # one per box, in the order of the boxes
    by_model: list[tuple[PoseEstimator, list[Prediction]]]  # each model that had boxes, in model order
    read_s: float  # the image and its depth
    predict_s: float  # the models' predict calls: crop, network, decoding (and translation when asked for)

    @property
    def seconds(self) -> float:
        """popcode's work on the image: reading it and the predictions."""
        return self.read_s + self.predict_s


class BoxInImage(Protocol):
    """One box to estimate, as :func:`group_by_image` reads it (the trainer's ``Instance`` is one)."""

    @property
    def image_path(self) -> Path: ...

    @property
    def K(self) -> np.ndarray | None: ...

    @property
    def box(self) -> tuple[float, float, float, float]: ...

    @property
    def obj_id(self) -> int: ...


def route_objects(estimators: Sequence[PoseEstimator], names: Sequence[str]) -> dict[int, int]:
    """Object id -> the index of the one model that estimates it; two models for one object is an error."""
    owner: dict[int, int] = {}
    for index, estimator in enumerate(estimators):
        for obj_id in estimator.metadata.objects:
            if obj_id in owner:
                raise PopcodeError(f"object {obj_id} is in both {names[owner[obj_id]]} and {names[index]}; "
                                   "give one model per object")
            owner[obj_id] = index
    return owner


def group_by_image(rows: Sequence[BoxInImage]) -> list[ImageBoxes[tuple[int, ...]]]:
    """The rows' boxes image by image (images in first-seen order, rows in theirs), so that each image is read once.

    An image's key is the indices of its rows, to put its predictions back in
    place; its camera is its first row's.
    """
    indices: dict[Path, list[int]] = defaultdict(list)
    for index, row in enumerate(rows):
        indices[row.image_path].append(index)
    return [ImageBoxes(tuple(found), path, rows[found[0]].K, [rows[i].box for i in found],
                       [rows[i].obj_id for i in found]) for path, found in indices.items()]


def estimate_images(estimators: Sequence[PoseEstimator], names: Sequence[str], images: Iterable[ImageBoxes[Key]],
                    **predict_kwargs: Any) -> Iterator[ImageEstimates[Key]]:
    """Each image's estimates, one image at a time: read once, every box predicted by the model of its object.

    ``names`` name the models in errors; ``predict_kwargs`` go to every
    :meth:`PoseEstimator.predict` call (``translation``, ``return_code``, ...).
    Two models for one object is refused before the first image is read; a
    :class:`PopcodeError` of one image names the image.
    """
    owner = route_objects(estimators, names)
    for boxes in images:
        try:
            estimates = _estimate_image(estimators, owner, boxes, predict_kwargs)
        except PopcodeError as error:
            if str(boxes.path) in str(error):
                raise
            raise PopcodeError(f"{boxes.path}: {error}") from error
        yield estimates


def _estimate_image(estimators: Sequence[PoseEstimator], owner: dict[int, int], boxes: ImageBoxes[Key],
                    predict_kwargs: dict[str, Any]) -> ImageEstimates[Key]:
    """Read one image and predict its boxes model by model, timing each part."""
    unknown = sorted(set(boxes.obj_ids) - set(owner))
    if unknown:
        raise PopcodeError(f"no model knows objects {unknown} (the models know {sorted(owner)})")
    started = time.perf_counter()
    image = read_image(boxes.path)
    if boxes.depth_path is not None:
        predict_kwargs = {**predict_kwargs, "depth": read_depth(boxes.depth_path), "depth_scale": boxes.depth_scale}
    read_s = time.perf_counter() - started
    placed: dict[int, Prediction] = {}  # box index -> its prediction
    by_model: list[tuple[PoseEstimator, list[Prediction]]] = []
    predict_s = 0.0
    for index, estimator in enumerate(estimators):
        chosen = [row for row, obj_id in enumerate(boxes.obj_ids) if owner[obj_id] == index]
        if not chosen:
            continue
        started = time.perf_counter()
        found = estimator.predict(image, [boxes.boxes[row] for row in chosen], K=boxes.K,
                                  obj_ids=[boxes.obj_ids[row] for row in chosen], **predict_kwargs)
        predict_s += time.perf_counter() - started
        placed.update(zip(chosen, found, strict=True))
        by_model.append((estimator, found))
    return ImageEstimates(boxes.key, image, [placed[row] for row in range(len(boxes.boxes))], by_model, read_s,
                          predict_s)
