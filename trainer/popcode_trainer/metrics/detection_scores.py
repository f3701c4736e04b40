"""2-D detection scores of a BOP split, as the BOP toolkit scores detections since the BOP22 challenge.

The toolkit writes each test image's ground truth as COCO annotations (its
``scripts/calc_gt_coco.py``) and scores a detections file with pycocotools' ``COCOeval``, iouType ``bbox``
(``scripts/eval_bop22_coco.py --ann_type=bbox``). Its conventions, kept here:

- The ground-truth box is amodal by default: the box of the object's whole silhouette inside the image (the
  full mask's box), here ``bbox_obj`` clipped to the image; ``box="modal"`` takes the visible part's box,
  ``bbox_visib``. A box from a mask counts pixels (``w = last - first + 1``), where ``scene_gt_info.json``'s
  (``calc_2d_bbox``) is one narrower, so the split's own boxes are widened by one pixel.
- Every instance with a visible pixel is annotated; one less than 10 % visible carries COCO's ``ignore``
  flag: a detection on it is neither a hit nor a false positive. The toolkit installs its authors' fork of
  pycocotools because upstream's ``COCOeval`` overwrites ``ignore`` with ``iscrowd``; :class:`_BopCocoEval`
  restores the fork's behaviour on upstream pycocotools.
- An instance's area, which sorts it into COCO's small / medium / large, is its visible pixel count
  (``px_count_visib``: the visible mask's area).
- The scores are COCOeval's twelve, under the toolkit's names: AP over IoU 0.50:0.05:0.95, AP50, AP75, AP of
  small, medium and large instances, AR with at most 1, 10 and 100 detections per image and object, AR of
  small, medium and large; and the mean detection time per image.

Where this differs from the toolkit: the images scored are the split's (``split_images`` that
``scene_gt.json`` annotates) rather than a targets file's; a detection of another image is refused, not
dropped; no detections at all score 0, not -1; a score COCO cannot define (no instance in an area range) is
None, not -1; detections of an object the split does not annotate at all are left out and counted
(``unannotated_detections``: no ground truth defines their AP). Beside COCO's scores: AP per object, and recall
at IoU 0.5 per visible fraction, taken from the same greedy matching COCOeval does (by score, one detection per
instance, best IoU first).
"""

from __future__ import annotations

import contextlib
import io
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from popcode_runtime.base.checks import number
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json
from popcode_runtime.base.image_size import image_size
from popcode_runtime.bop.detections import Detection
from popcode_runtime.bop.split import (
    BOP19_MIN_VISIB_FRACT,
    int_keys,
    json_field,
    scene_folders,
    scene_ground_truth,
    split_images,
)

BOX_TYPES = ("amodal", "modal")  # the toolkit's bbox_type
COCO_SCORES = ("AP", "AP50", "AP75", "AP_small", "AP_medium", "AP_large",
               "AR1", "AR10", "AR100", "AR_small", "AR_medium", "AR_large")
"""``COCOeval.stats`` in order, under the names of the toolkit's ``scores_bop22_coco_bbox.json``."""
IGNORE_BELOW_VISIB_FRACT = BOP19_MIN_VISIB_FRACT  # calc_gt_coco.py: ignore instances under 10 % visible
RECALL_IOU = 0.5
VISIBILITY_BINS = ((0.1, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 0.9), (0.9, 1.0))
GOAL_MIN_VISIB_FRACT = 0.3  # the detector's goal: recall of instances at least 30 % visible


@dataclass(frozen=True)
class VisibilityRecall:
    """How many instances with a visible fraction in ``[low, high)`` (``high`` 1 included) a detection found."""

    low: float
    high: float
    instances: int
    found: int

    @property
    def recall(self) -> float | None:
        """None where the range holds no instance."""
        return self.found / self.instances if self.instances else None

    def to_dict(self) -> dict[str, Any]:
        return {"visib_fract": [self.low, self.high], "instances": self.instances, "found": self.found,
                "recall": self.recall}


@dataclass(frozen=True)
class DetectionScores:
    """A split's detection scores; ``coco`` maps each of :data:`COCO_SCORES` to its value (None: undefined)."""

    box: str  # "amodal" or "modal"
    min_score: float  # the recall's: detections scored lower find nothing
    images: int
    instances: int  # annotated: at least one visible pixel
    ignored_instances: int  # of those, less than 10 % visible
    detections: int
    coco: dict[str, float | None]
    mean_time_per_image_s: float | None  # None where a detection's time is unknown
    ap_per_object: dict[int, float | None]  # None: no instance of the object to find
    recall_by_visibility: tuple[VisibilityRecall, ...]  # at IoU 0.5, one per VISIBILITY_BINS
    recall_goal: VisibilityRecall  # at IoU 0.5, instances at least 30 % visible
    unannotated_detections: dict[int, int]  # object -> detections of it, an object the split does not annotate

    def to_dict(self) -> dict[str, Any]:
        return {
            "box": self.box, "min_score": self.min_score, "images": self.images, "instances": self.instances,
            "ignored_instances": self.ignored_instances, "detections": self.detections, **self.coco,
            "mean_time_per_image_s": self.mean_time_per_image_s,
            "ap_per_object": {str(obj_id): ap for obj_id, ap in self.ap_per_object.items()},
            "recall_iou50_by_visibility": [recall.to_dict() for recall in self.recall_by_visibility],
            "recall_iou50_goal": self.recall_goal.to_dict(),
            "unannotated_detections": {str(obj_id): count for obj_id, count in self.unannotated_detections.items()},
        }


@dataclass(frozen=True)
class GroundTruthInstance:
    image: tuple[int, int]  # scene id, image id
    obj_id: int
    box: tuple[float, float, float, float]  # COCO's: w and h count pixels
    area_px: int  # visible pixels
    visib_fract: float


class _BopCocoEval(COCOeval):
    """``COCOeval`` that keeps each ground-truth annotation's own ``ignore`` flag, as the toolkit's pycocotools.

    The fork the toolkit installs (MartinSmeyer/cocoapi) differs from upstream's evaluation in one line of
    ``_prepare``: upstream sets ``ignore`` from ``iscrowd``, which would count the toolkit's ignored instances
    (under 10 % visible) as instances to find. Marking them ``iscrowd`` instead would change their IoU.
    """

    def _prepare(self) -> None:
        flags = {annotation["id"]: annotation["ignore"] for annotation in self.cocoGt.dataset["annotations"]}
        super()._prepare()
        for image_annotations in self._gts.values():
            for annotation in image_annotations:
                annotation["ignore"] = flags[annotation["id"]]


def detection_scores(split_dir: str | Path, detections: Sequence[Detection], box: str = "amodal",
                     min_score: float = 0.0) -> DetectionScores:
    """Score ``detections`` (boxes ``x, y, w, h`` px, COCO's convention) against the split's ground truth.

    ``min_score`` only bounds the recall per visible fraction; COCO's AP ranks every detection by its score.
    A detection of an image the split does not annotate, or a split without any instance to find, is
    refused in one line.
    """
    if box not in BOX_TYPES:
        raise PopcodeError(f"box must be one of {list(BOX_TYPES)}, got {box!r}")
    min_score = number(min_score, "min_score", 0.0, 1.0)
    split_dir = Path(split_dir)
    images, instances = ground_truth_instances(split_dir, box)
    _refuse_other_images(detections, images, split_dir)
    scored = [instance for instance in instances if instance.visib_fract >= IGNORE_BELOW_VISIB_FRACT]
    if not scored:
        raise PopcodeError(f"{split_dir}: no ground-truth instance at least {IGNORE_BELOW_VISIB_FRACT:.0%} visible "
                           f"in its {len(images)} annotated images; there is nothing to detect")
    annotated = {instance.obj_id for instance in instances}
    unannotated = Counter(d.obj_id for d in detections if d.obj_id not in annotated)
    evaluator = _evaluate(images, instances, [d for d in detections if d.obj_id in annotated])
    found = _found_instances(evaluator, min_score)

    def recall(low: float, high: float) -> VisibilityRecall:
        ids = [index for index, instance in enumerate(instances, start=1)
               if low <= instance.visib_fract < high or instance.visib_fract == high == 1.0]
        return VisibilityRecall(low, high, len(ids), sum(index in found for index in ids))

    return DetectionScores(
        box=box, min_score=min_score, images=len(images), instances=len(instances),
        ignored_instances=len(instances) - len(scored), detections=len(detections),
        coco={name: _defined(value) for name, value in zip(COCO_SCORES, evaluator.stats, strict=True)},
        mean_time_per_image_s=_mean_time_per_image(detections),
        ap_per_object=_ap_per_object(evaluator),
        recall_by_visibility=tuple(recall(low, high) for low, high in VISIBILITY_BINS),
        recall_goal=recall(GOAL_MIN_VISIB_FRACT, 1.0),
        unannotated_detections=dict(sorted(unannotated.items())),
    )


def ground_truth_instances(split_dir: Path, box: str) -> tuple[list[tuple[int, int]], list[GroundTruthInstance]]:
    """The split's annotated images (those with an image file and a ``scene_gt.json`` entry) and their
    instances with a visible pixel, boxes in COCO's convention."""
    files = split_images(split_dir)
    box_kind = "bbox_obj" if box == "amodal" else "bbox_visib"
    images: list[tuple[int, int]] = []
    instances: list[GroundTruthInstance] = []
    for scene_dir in scene_folders(split_dir):
        info_path = scene_dir / "scene_gt_info.json"
        infos = int_keys(read_json(info_path), info_path)
        for im_id, gts in scene_ground_truth(scene_dir, box_kind, min_visib_fract=0.0):
            key = (int(scene_dir.name), im_id)
            if key not in files:
                continue
            images.append(key)
            size = _image_size(files[key].path) if box == "amodal" and gts else None
            for gt in gts:
                area_px = int(json_field(infos[im_id][gt.gt_index], "px_count_visib", info_path, gt.where, 1)[0])
                coco_box = _clipped_coco_box(gt.box, size) if size else _coco_box(gt.box)
                if area_px >= 1 and coco_box is not None:
                    instances.append(GroundTruthInstance(key, gt.obj_id, coco_box, area_px, gt.visib_fract))
    return images, instances


def _image_size(path: Path) -> tuple[int, int]:
    size = image_size(path)
    if size is None:
        raise PopcodeError(f"{path}: cannot read the image's size from its header (PNG, JPEG, BMP or PNM)")
    return size


def _coco_box(box: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """A ``calc_2d_bbox`` box (``w`` from the first pixel to the last) as a mask's box (``w`` counts pixels)."""
    x, y, w, h = box
    return x, y, w + 1.0, h + 1.0


def _clipped_coco_box(box: tuple[float, float, float, float],
                      size: tuple[int, int]) -> tuple[float, float, float, float] | None:
    """The part of a ``calc_2d_bbox`` box inside an image of ``(width, height)``, as a mask's box; None when
    none of it is inside."""
    x, y, w, h = box
    width, height = size
    x0, y0 = max(x, 0.0), max(y, 0.0)
    x1, y1 = min(x + w, width - 1.0), min(y + h, height - 1.0)
    if x1 < x0 or y1 < y0:
        return None
    return x0, y0, x1 - x0 + 1.0, y1 - y0 + 1.0


def _refuse_other_images(detections: Sequence[Detection], images: list[tuple[int, int]], split_dir: Path) -> None:
    known = set(images)
    outside = [detection for detection in detections if detection.image_key not in known]
    if outside:
        first = outside[0]
        raise PopcodeError(f"{len(outside)} detections are of images that {split_dir} does not annotate (first: "
                           f"scene {first.scene_id}, image {first.im_id}); score them against their own split")


def _evaluate(images: list[tuple[int, int]], instances: list[GroundTruthInstance],
              detections: Sequence[Detection]) -> COCOeval:
    """COCOeval run to its summary, with pycocotools' progress lines kept off stdout.

    Annotation ids are 1 + the instance's index (COCOeval records a match as the matched id, so 0 would read
    as no match); image ids are 1 + the image's index.
    """
    image_ids = {key: index for index, key in enumerate(images, start=1)}
    categories = sorted({instance.obj_id for instance in instances} | {d.obj_id for d in detections})
    ground_truth = {
        "images": [{"id": image_id} for image_id in image_ids.values()],
        "categories": [{"id": obj_id, "name": str(obj_id)} for obj_id in categories],
        "annotations": [{"id": index, "image_id": image_ids[instance.image], "category_id": instance.obj_id,
                         "bbox": list(instance.box), "area": instance.area_px, "iscrowd": 0,
                         "ignore": int(instance.visib_fract < IGNORE_BELOW_VISIB_FRACT)}
                        for index, instance in enumerate(instances, start=1)],
    }
    results = [{"image_id": image_ids[d.image_key], "category_id": d.obj_id, "bbox": list(d.box), "score": d.score}
               for d in detections]
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = _indexed(ground_truth)
        # loadRes reads its first result's keys, so no detections are an empty set built alike (AP 0)
        coco_dt = coco_gt.loadRes(results) if results else _indexed({**ground_truth, "annotations": []})
        evaluator = _BopCocoEval(coco_gt, coco_dt, "bbox")
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    return evaluator


def _indexed(dataset: dict[str, Any]) -> COCO:
    """A COCO object of an in-memory dataset (upstream's constructor only reads files)."""
    coco = COCO()
    coco.dataset = dataset
    coco.createIndex()
    return coco


def _defined(value: float) -> float | None:
    """COCOeval's -1 (no instance to score) as None."""
    return None if value < 0 else float(value)


def _ap_per_object(evaluator: COCOeval) -> dict[int, float | None]:
    """Each object's AP as COCOeval's summary averages it for all objects: precision at every IoU threshold
    and recall step, instances of every area, at most 100 detections."""
    params = evaluator.params
    precision = evaluator.eval["precision"][:, :, :, params.areaRngLbl.index("all"), params.maxDets.index(100)]
    per_object = {}
    for index, obj_id in enumerate(params.catIds):
        defined = precision[:, :, index][precision[:, :, index] > -1]
        per_object[obj_id] = float(defined.mean()) if defined.size else None
    return per_object


def _found_instances(evaluator: COCOeval, min_score: float) -> set[int]:
    """Annotation ids that COCOeval matched at IoU 0.5 to a detection scoring at least ``min_score``.

    The matching is greedy in score order, so dropping the detections below ``min_score`` would leave the
    higher ones' matches as they are: reading the score of each match is the same as matching again.
    """
    params = evaluator.params
    threshold = int(np.flatnonzero(np.isclose(params.iouThrs, RECALL_IOU))[0])
    all_areas = params.areaRng[params.areaRngLbl.index("all")]
    found: set[int] = set()
    for result in evaluator.evalImgs:
        if result is None or result["aRng"] != all_areas:
            continue
        scores = dict(zip(result["dtIds"], result["dtScores"], strict=True))
        for gt_id, dt_id in zip(result["gtIds"], result["gtMatches"][threshold], strict=True):
            if dt_id > 0 and scores[int(dt_id)] >= min_score:
                found.add(gt_id)
    return found


def _mean_time_per_image(detections: Sequence[Detection]) -> float | None:
    """The mean of each image's detection time (the toolkit's ``average_time_per_image``); an image's
    detections must agree on it, as BOP's time is the whole image's."""
    times: dict[tuple[int, int], float] = {}
    for detection in detections:
        if detection.time_s < 0:
            return None
        known = times.setdefault(detection.image_key, detection.time_s)
        if abs(known - detection.time_s) > 1e-3:
            raise PopcodeError(f"scene {detection.scene_id}, image {detection.im_id}: detections give the image's "
                               f"time as {known:g} s and {detection.time_s:g} s; BOP's time is per image, the same "
                               f"in each of its detections")
    return float(np.mean(list(times.values()))) if times else None
