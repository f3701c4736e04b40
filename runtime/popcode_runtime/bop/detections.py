"""2-D detections to estimate poses for: a detector's boxes in the BOP challenge's format, or a split's own boxes.

The BOP challenge's default detections are a JSON list of
``{"scene_id", "image_id", "category_id", "bbox": [x, y, w, h], "score", "time"}``
(``category_id`` is the object id, ``time`` the detector's seconds for the whole
image, repeated in each of its detections). Every entry is checked when the file
is read, so a malformed file is refused with the entry and field named before
any image is processed.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..base.errors import PopcodeError
from ..base.files import read_json
from .split import BOP19_MIN_VISIB_FRACT, BOX_KINDS, scene_folders, scene_ground_truth

MAX_DETECTIONS = 5_000_000  # far more than any BOP test set; bounds what a file can make us hold


@dataclass(frozen=True)
class Detection:
    """One box to estimate a pose for (BOP conventions: ``x, y, w, h`` pixels, object id)."""

    scene_id: int
    im_id: int
    obj_id: int
    box: tuple[float, float, float, float]
    score: float = 1.0  # the detector's
    time_s: float = -1.0  # the detector's seconds for the whole image; -1: unknown

    @property
    def image_key(self) -> tuple[int, int]:
        return self.scene_id, self.im_id


def _integer(entry: Mapping[str, Any], key: str, where: str) -> int:
    value = entry.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise PopcodeError(f"{where}: '{key}' must be a non-negative integer, got {value!r}")
    return value


def _finite(entry: Mapping[str, Any], key: str, where: str, default: float | None = None) -> float:
    value = entry.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise PopcodeError(f"{where}: '{key}' must be a finite number, got {value!r}")
    return float(value)


def _score(entry: Mapping[str, Any], where: str) -> float:
    """The detector's confidence in [0, 1]: it scales each estimate's score, so a value outside would rank a more
    confident estimate lower (a logit or a percentage, say)."""
    score = _finite(entry, "score", where)
    if not 0.0 <= score <= 1.0:
        raise PopcodeError(f"{where}: 'score' must lie in [0, 1] (a confidence), got {score!r}")
    return score


def _box(entry: Mapping[str, Any], where: str) -> tuple[float, float, float, float]:
    value = entry.get("bbox")
    if not isinstance(value, list) or len(value) != 4 or any(
            isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in value):
        raise PopcodeError(f"{where}: 'bbox' must be 4 finite numbers [x, y, w, h], got {value!r}")
    if value[2] <= 0 or value[3] <= 0:
        raise PopcodeError(f"{where}: 'bbox' {value} has no area (w and h must be positive)")
    return tuple(float(v) for v in value)


def read_detections(path: str | Path) -> list[Detection]:
    """Every detection of a BOP default-detections JSON file, each checked; the first bad entry is named."""
    path = Path(path)
    if path.is_dir():
        raise PopcodeError(f"detections {path} is a folder, not a JSON file")
    entries = read_json(path)
    if not isinstance(entries, list):
        raise PopcodeError(f"{path}: expected a JSON list of detections ({{scene_id, image_id, category_id, bbox, "
                           f"score, time}}), got {type(entries).__name__}")
    if len(entries) > MAX_DETECTIONS:
        raise PopcodeError(f"{path}: {len(entries)} detections exceed the limit of {MAX_DETECTIONS}")
    detections = []
    for index, entry in enumerate(entries):
        where = f"{path}: detection {index}"
        if not isinstance(entry, Mapping):
            raise PopcodeError(f"{where} must be a JSON object, got {type(entry).__name__}")
        detections.append(Detection(
            scene_id=_integer(entry, "scene_id", where), im_id=_integer(entry, "image_id", where),
            obj_id=_integer(entry, "category_id", where), box=_box(entry, where),
            score=_score(entry, where), time_s=_finite(entry, "time", where, default=-1.0),
        ))
    return detections


def ground_truth_boxes(split_dir: str | Path, box_kind: str = "bbox_obj",
                       min_visib_fract: float = BOP19_MIN_VISIB_FRACT) -> list[Detection]:
    """The split's own boxes (``scene_gt_info.json``) as detections of score 1: the paper's GT-box protocol.

    Instances with less than ``min_visib_fract`` visible or an empty box are left out
    (:func:`popcode_runtime.bop.split.scene_ground_truth`, the walk the trainer's reader takes too).
    """
    if box_kind not in BOX_KINDS:
        raise PopcodeError(f"box kind must be one of {list(BOX_KINDS)}, got {box_kind!r}")
    return [Detection(gt.scene_id, gt.im_id, gt.obj_id, gt.box)
            for scene_dir in scene_folders(Path(split_dir))
            for _, selected in scene_ground_truth(scene_dir, box_kind, min_visib_fract)
            for gt in selected]
