"""The evaluation split: the ground-truth instances of one or more BOP splits that every method is scored on."""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT

from ...data.bop import Instance, read_bop_split


@dataclass(frozen=True)
class DetectorBoxes:
    """How a split's boxes were replaced by a detector's (``detector_boxes.with_detector_boxes``)."""

    preset: str  # the box-noise preset's name ("custom" for a noise model of no preset)
    seed: int
    iou: np.ndarray  # (N,) each instance's box against its ground-truth box, split order


@dataclass(frozen=True)
class EvalSplit:
    """The ground-truth instances to evaluate and the objects they show.

    ``detector_boxes`` is None while each instance carries its ground-truth box (the paper's protocol).
    """

    instances: list[Instance]
    models_info: dict[int, dict[str, Any]]
    models_dir: Path
    detector_boxes: DetectorBoxes | None = field(default=None, compare=False)

    @property
    def obj_ids(self) -> list[int]:
        return sorted({inst.obj_id for inst in self.instances})


def read_eval_split(split_dirs: Sequence[str | Path], models_dir: str | Path, obj_ids: Iterable[int] | None = None,
                    max_instances: int | None = None, min_visib_fract: float = BOP19_MIN_VISIB_FRACT) -> EvalSplit:
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


def restrict_to_objects(split: EvalSplit, obj_ids: Iterable[int]) -> EvalSplit:
    """The split's instances of ``obj_ids`` only."""
    wanted = set(obj_ids)
    chosen = np.array([inst.obj_id in wanted for inst in split.instances], dtype=bool)
    kept = [inst for inst, keep in zip(split.instances, chosen, strict=True) if keep]
    boxes = split.detector_boxes
    if boxes is not None:
        boxes = DetectorBoxes(boxes.preset, boxes.seed, boxes.iou[chosen])
    return EvalSplit(kept, {k: v for k, v in split.models_info.items() if k in wanted}, split.models_dir, boxes)
