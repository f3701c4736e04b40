"""What a popcode detector's ONNX file says about itself (docs/design.md#detector-contract).

A detector is a network of its own file, beside the pose models: one grey
frame of a fixed size in, a score per object class and a box for every place
of its feature maps out; thresholds and non-maximum suppression run in the
runtime (:mod:`popcode_runtime.inference.detector`). As for the pose models,
everything the runtime needs travels in ``metadata_props`` under
``popcode_detector.*`` keys, each value JSON, so a detector file without them
is refused in one line.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from ..base.checks import integer, mapping, number
from ..base.errors import PopcodeError
from ..base.files import parse_json
from ..base.limits import MAX_METADATA_CHARS, MAX_OBJECTS

DETECTOR_FORMAT_VERSION = 1
DETECTOR_INPUT = "image"  # (1, 1, H, W) float32 grey in [0, 1]
DETECTOR_BOXES = "boxes"  # (1, L, 4) float32 x0, y0, x1, y1 in the input's pixels
DETECTOR_SCORES = "scores"  # (1, L, C) float32 in [0, 1], C the object ids in metadata order
# The grey a detector's graph first normalises to 0 ((x - mean) / std): the value its convolutions see beyond the
# input's border, and so the runtime's pad of a letterboxed frame (the trainer's network takes it from here).
DETECTOR_INPUT_MEAN = 0.45
MIN_SIDE, MAX_SIDE = 32, 2048  # the detector's input side [px]
MAX_DETECTIONS = 1000  # per frame; the runtime's pose call takes at most MAX_BOXES_PER_CALL boxes
PREFIX = "popcode_detector."


@dataclass(frozen=True)
class DetectorMetadata:
    """A detector's input size, objects and defaults for thresholds, as its export wrote them.

    ``obj_ids[c]`` is the BOP object id of score column ``c``. ``score_threshold``
    keeps boxes scoring at least it; ``nms_iou`` suppresses a box overlapping a
    better one of the same object by more than it; at most ``max_detections``
    boxes a frame are kept. ``training`` records what it was trained on.
    """

    obj_ids: tuple[int, ...]
    input_width: int
    input_height: int
    score_threshold: float = 0.3
    nms_iou: float = 0.5
    max_detections: int = 100
    training: dict[str, Any] = field(default_factory=dict)
    format_version: int = DETECTOR_FORMAT_VERSION

    def __post_init__(self) -> None:
        ids = self.obj_ids
        if not isinstance(ids, (list, tuple)) or not ids:
            raise PopcodeError(f"a detector needs a non-empty list of object ids, got {ids!r}")
        if len(ids) > MAX_OBJECTS:
            raise PopcodeError(f"the detector lists {len(ids)} objects, more than the limit of {MAX_OBJECTS}")
        checked = tuple(integer(v, "detector object id", 0, 10**18) for v in ids)
        if len(set(checked)) != len(checked):
            raise PopcodeError(f"the detector lists an object id twice: {list(checked)}")
        object.__setattr__(self, "obj_ids", checked)
        object.__setattr__(self, "input_width", integer(self.input_width, "detector input width", MIN_SIDE, MAX_SIDE))
        object.__setattr__(self, "input_height", integer(self.input_height, "detector input height", MIN_SIDE,
                                                         MAX_SIDE))
        self.check_thresholds(self.score_threshold, self.nms_iou, self.max_detections)
        mapping(self.training, "detector training")

    @staticmethod
    def check_thresholds(score_threshold: float, nms_iou: float, max_detections: int) -> None:
        """The thresholds a detector runs with, from its file or a caller: absurd ones are refused in one line."""
        number(score_threshold, "detector score threshold", 0.0, 1.0)
        if score_threshold <= 0.0:
            raise PopcodeError("detector score threshold must be above 0 (at 0 every place of the image is a box)")
        number(nms_iou, "detector NMS IoU", 0.0, 1.0)
        if nms_iou <= 0.0:
            raise PopcodeError("detector NMS IoU must be above 0 (at 0 every overlap suppresses)")
        integer(max_detections, "detector max detections", 1, MAX_DETECTIONS)

    def to_props(self) -> dict[str, str]:
        """``metadata_props`` entries: one key per field, JSON values."""
        return {
            f"{PREFIX}format_version": json.dumps(self.format_version),
            f"{PREFIX}obj_ids": json.dumps(list(self.obj_ids)),
            f"{PREFIX}input": json.dumps({"width": self.input_width, "height": self.input_height}),
            f"{PREFIX}thresholds": json.dumps({"score": self.score_threshold, "nms_iou": self.nms_iou,
                                               "max_detections": self.max_detections}),
            f"{PREFIX}training": json.dumps(self.training),
        }

    @classmethod
    def from_props(cls, props: Mapping[str, str]) -> DetectorMetadata:
        """Parse ``metadata_props``; a pose model or any other ONNX file is told apart in one line."""
        if f"{PREFIX}format_version" not in props:
            pose = " (it is a popcode pose model: give it as MODEL, not as --detector)" \
                if "popcode.format_version" in props else ""
            raise PopcodeError(f"not a popcode detector: its metadata has no '{PREFIX}format_version'{pose}")
        chars = sum(len(value) for value in props.values())
        if chars > MAX_METADATA_CHARS:
            raise PopcodeError(f"the detector's metadata holds {chars:,} characters, more than the limit of "
                               f"{MAX_METADATA_CHARS:,}")

        def load(key: str) -> Any:
            if PREFIX + key not in props:
                raise PopcodeError(f"detector metadata lacks '{PREFIX}{key}'")
            return parse_json(props[PREFIX + key], f"detector metadata '{PREFIX}{key}'")

        version = load("format_version")
        if version != DETECTOR_FORMAT_VERSION or isinstance(version, bool):
            raise PopcodeError(f"detector format version {version!r} is not supported by this runtime (it reads "
                               f"{DETECTOR_FORMAT_VERSION})")
        size = mapping(load("input"), f"detector metadata '{PREFIX}input'")
        thresholds = mapping(load("thresholds"), f"detector metadata '{PREFIX}thresholds'")
        return cls(obj_ids=load("obj_ids"), input_width=size.get("width"), input_height=size.get("height"),
                   score_threshold=thresholds.get("score"), nms_iou=thresholds.get("nms_iou"),
                   max_detections=thresholds.get("max_detections"), training=load("training"), format_version=version)
