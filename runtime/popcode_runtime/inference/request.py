"""A ``PoseEstimator.predict`` call's arguments, checked before any work, as one ``PredictRequest``.

Every argument is checked against the model it goes to (its rotation frame,
representation, objects and output size) and against the runtime's bounds, so
that a bad call raises one :class:`PopcodeError` before a crop is cut.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..base.checks import flag, integer
from ..base.errors import PopcodeError
from ..depth.icp import require_small_gicp
from ..depth.surface_fit import ObjectSurface, check_depth
from ..geometry.camera import camera_for_image, parse_camera_matrix
from ..geometry.crop import check_image
from ..model.metadata import ModelMetadata, Representation, RotationFrame

MAX_BOXES_PER_CALL = 10_000  # predict runs them in chunks; a robot's image holds far fewer
MAX_TOP_K = 100
MEMORY_BUDGET_BYTES = 1 << 30  # crops + outputs held at once by one call


@dataclass(frozen=True)
class PredictRequest:
    """What one :meth:`PoseEstimator.predict` call asks for, checked."""

    image: np.ndarray  # grey or RGB, as :func:`check_image` passes it
    ids: list[int | None]  # the object of each box; None for a model of several objects not told which
    camera: np.ndarray | None  # K, 3x3, in the image's pixels
    return_code: bool
    top_k: int
    translation: bool
    depth_mm: np.ndarray | None  # (H, W) float32 mm, 0: no reading
    refine_depth: bool


def check_request(meta: ModelMetadata, image: np.ndarray, boxes: Sequence[Sequence[float]], *,
                  K: Sequence[float] | np.ndarray | None, return_code: bool, obj_ids: Sequence[int] | None,
                  top_k: int, translation: bool, depth: np.ndarray | None, depth_scale: float, refine_depth: bool,
                  object_surface: Callable[[int | None], ObjectSurface],
                  crop_origin: Sequence[float] | np.ndarray | None) -> PredictRequest:
    """The arguments of :meth:`PoseEstimator.predict` checked for the model ``meta`` (see its docstring);
    ``object_surface`` refuses an object whose surface points depth would need and the model lacks. ``K`` is
    checked against the image (and moved into a crop's pixels by ``crop_origin``): another image's camera would
    silently turn an allocentric model's rotations and misplace every translation."""
    return_code, translation = flag(return_code, "return_code"), flag(translation, "translation")
    refine_depth = flag(refine_depth, "refine_depth")
    top_k = integer(top_k, "top_k", 1, MAX_TOP_K)
    if refine_depth and depth is None:
        raise PopcodeError("refine_depth refines the pose against a depth image: pass depth")
    translation = translation or depth is not None
    camera = _camera(meta, K, translation, depth is not None)
    if crop_origin is not None and camera is None:
        raise PopcodeError("crop_origin moves K's principal point into the crop: pass the camera matrix K")
    if top_k > 1 and meta.representation != Representation.POPULATION_CODE:
        raise PopcodeError(f"hypotheses (top_k > 1) need a population-code model, this one is {meta.representation}")
    if obj_ids is None and len(meta.objects) > 1 and (translation or top_k > 1):
        raise PopcodeError(f"this model knows objects {sorted(meta.objects)}: pass the object id of each box")
    check_box_count(boxes)
    if return_code and len(boxes) * meta.output_dim * 4 > MEMORY_BUDGET_BYTES:
        raise PopcodeError(f"returning the codes of {len(boxes)} boxes exceeds the memory budget of "
                           f"{MEMORY_BUDGET_BYTES >> 20} MiB; ask for fewer boxes at a time")
    ids = object_ids(meta, len(boxes), obj_ids)
    image = check_image(image)
    if camera is not None:
        camera = camera_for_image(camera, image.shape, crop_origin)
    depth_mm = None
    if depth is not None:
        depth_mm = check_depth(depth, image.shape, depth_scale)
        for obj_id in sorted(set(ids)):
            object_surface(obj_id)
        if refine_depth:
            require_small_gicp()
    return PredictRequest(image, ids, camera, return_code, top_k, translation, depth_mm, refine_depth)


def _camera(meta: ModelMetadata, K: Sequence[float] | np.ndarray | None, translation: bool,
            depth: bool) -> np.ndarray | None:
    """The checked camera matrix; refused when missing and the model's frame or the translation needs it."""
    if K is not None:
        return parse_camera_matrix(K)
    if meta.rotation_frame == RotationFrame.ALLOCENTRIC or translation:
        needs = ("translation from depth" if depth else "translation from the box") if translation \
            else "this model predicts allocentric rotations"
        raise PopcodeError(f"{needs}: pass the camera matrix K")
    return None


def object_ids(meta: ModelMetadata, count: int, obj_ids: Sequence[int] | None) -> list[int | None]:
    """The object of each of ``count`` boxes; unknown (None) for a model of several objects when not given."""
    known = sorted(meta.objects)
    if obj_ids is None:
        return [known[0] if len(known) == 1 else None] * count
    if isinstance(obj_ids, (str, bytes)) or not isinstance(obj_ids, (Sequence, np.ndarray)):
        raise PopcodeError(f"obj_ids must be a list of integers, got {type(obj_ids).__name__}")
    if len(obj_ids) != count:
        raise PopcodeError(f"got {len(obj_ids)} object ids for {count} boxes")
    ids = [integer(i, "an object id") for i in obj_ids]
    unknown = sorted(set(ids) - set(known))
    if unknown:
        raise PopcodeError(f"object ids {unknown} are not in this model (it knows {known})")
    return ids


def check_box_count(boxes: Sequence[Sequence[float]]) -> None:
    """Boxes are a non-empty list of at most :data:`MAX_BOXES_PER_CALL`."""
    if isinstance(boxes, (str, bytes)) or not hasattr(boxes, "__len__") or not hasattr(boxes, "__getitem__"):
        raise PopcodeError(f"boxes must be a list of (x, y, w, h), got {type(boxes).__name__}")
    if len(boxes) == 0:
        raise PopcodeError("no boxes given")
    if len(boxes) > MAX_BOXES_PER_CALL:
        raise PopcodeError(f"{len(boxes)} boxes in one call; the limit is {MAX_BOXES_PER_CALL}")
