"""Detector-like boxes for evaluation: each ground-truth box with a box-noise preset's error, seeded per instance.

Each instance's box is drawn from its own generator, seeded by ``(seed, scene_id,
im_id, gt_index)``, so it depends neither on which other instances are evaluated
nor on the method: ``popcode-train evaluate --box-noise`` gives every method the
same boxes, and the detections file of ``popcode-train detections`` (for
``popcode run --detections``) holds those boxes too. Boxes are clipped to the
image (:func:`popcode_trainer.data.box_noise.noisy_box`), whose size is read from
the file's header. The ``none`` preset keeps each box exactly as the split gives
it, not clipped: the ground-truth-box protocol itself, with IoU 1.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from popcode_runtime.base.checks import integer
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.image_size import image_size
from popcode_runtime.bop.detections import Detection
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT, scene_folders, scene_ground_truth, split_images
from popcode_runtime.geometry.crop import read_image

from ...data.box_noise import BOX_NOISE_PRESETS, Box, BoxNoise, box_iou, noisy_box
from .split import DetectorBoxes, EvalSplit


def image_size_px(path: str | Path) -> tuple[int, int]:
    """``(width, height)`` of an image file from its header; decoded only where the header reader knows no format."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"image file not found: {path}")
    size = image_size(path)
    if size is None:
        height, width = read_image(path).shape[:2]
        return width, height
    return int(size[0]), int(size[1])


def preset_name(noise: BoxNoise) -> str:
    """The name of the preset ``noise`` is, or ``custom``."""
    return next((name for name, preset in BOX_NOISE_PRESETS.items() if preset == noise), "custom")


def detector_box(box: Sequence[float], noise: BoxNoise, seed: int, scene_id: int, im_id: int, gt_index: int,
                 image_size_wh: tuple[int, int] | None) -> Box:
    """The detector's box for ground-truth instance ``gt_index`` of image ``im_id`` in scene ``scene_id``.

    ``image_size_wh`` (width, height) clips it; it may be None for the ``none`` preset, which returns ``box``.
    """
    if noise.is_none:
        return tuple(float(v) for v in box)
    rng = np.random.default_rng((seed, scene_id, im_id, gt_index))
    return noisy_box(box, noise, rng, image_size_wh)


def _checked_seed(seed: int) -> int:
    return integer(seed, "the box-noise seed", 0)


def with_detector_boxes(split: EvalSplit, noise: BoxNoise, seed: int = 0) -> EvalSplit:
    """The split with each instance's box replaced by its :func:`detector_box`, and every box's IoU with the truth.

    Replace once, before any method runs, so that every method and the translation fit see the same boxes.
    """
    seed = _checked_seed(seed)
    if split.detector_boxes is not None:
        raise PopcodeError(f"the split's boxes are already a detector's (preset {split.detector_boxes.preset!r}); "
                           "replace the ground-truth boxes once")
    sizes: dict[Path, tuple[int, int]] = {}
    instances, iou = [], []
    for inst in split.instances:
        if not noise.is_none and inst.image_path not in sizes:
            sizes[inst.image_path] = image_size_px(inst.image_path)
        box = detector_box(inst.box, noise, seed, inst.scene_id, inst.im_id, inst.gt_index,
                           sizes.get(inst.image_path))
        instances.append(dataclasses.replace(inst, box=box))
        iou.append(box_iou(inst.box, box))
    return EvalSplit(instances, split.models_info, split.models_dir,
                     DetectorBoxes(preset_name(noise), seed, np.array(iou, dtype=np.float64)))


def split_detections(split_dir: str | Path, noise: BoxNoise, seed: int = 0, box_kind: str = "bbox_obj",
                     min_visib_fract: float = BOP19_MIN_VISIB_FRACT) -> tuple[list[Detection], np.ndarray]:
    """The detector's box (:func:`detector_box`) of every ground-truth instance the split's walk selects, with
    each one's IoU with its true box ``(D,)``: the boxes ``evaluate --box-noise`` gives the same instances."""
    seed = _checked_seed(seed)
    split_dir = Path(split_dir)
    images = split_images(split_dir)
    detections, iou = [], []
    for scene_dir in scene_folders(split_dir):
        for im_id, selected in scene_ground_truth(scene_dir, box_kind, min_visib_fract):
            if not selected:
                continue
            image = images.get((int(scene_dir.name), im_id))
            if image is None:
                raise PopcodeError(f"{scene_dir}: scene_gt.json has image {im_id}, but there is no such image file")
            size = None if noise.is_none else image_size_px(image.path)
            for gt in selected:
                box = detector_box(gt.box, noise, seed, gt.scene_id, gt.im_id, gt.gt_index, size)
                detections.append(Detection(gt.scene_id, gt.im_id, gt.obj_id, box))
                iou.append(box_iou(gt.box, box))
    if not detections:
        raise PopcodeError(f"{split_dir}: no ground-truth instance with visib_fract >= {min_visib_fract} and a "
                           f"{box_kind} box")
    return detections, np.array(iou, dtype=np.float64)


def detections_json(detections: Sequence[Detection]) -> list[dict]:
    """The BOP challenge's default-detections entries (``time`` -1: unknown), as ``popcode run`` reads them."""
    return [{"scene_id": d.scene_id, "image_id": d.im_id, "category_id": d.obj_id, "bbox": list(d.box),
             "score": d.score, "time": d.time_s} for d in detections]
