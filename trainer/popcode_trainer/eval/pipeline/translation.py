"""Translation from the box in evaluation: the runtime's fit, full 6-D poses with it, and its error.

The paper scores rotations with the ground-truth translation; a robot has only
the box. Each instance is placed as the runtime places it
(:func:`popcode_runtime.geometry.translation.translation_from_box` with the points the
model's metadata carries), so that full 6-D poses can be scored beside the
paper's protocol (:func:`full_pose`) and the translation error be reported on
its own, in mm and as a share of the distance.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.translation import object_points_mm, translation_from_box

from ...data.bop import Instance
from ...metrics.pose_errors import translation_error_mm
from ...metrics.recall import InstanceErrors
from .split_metrics import SplitMetrics

SUMMARY_COLUMNS = {
    "median_te_mm": "median te [mm]",
    "mean_te_mm": "mean te [mm]",
    "median_te_percent": "median te [% of ‖t‖]",
    "mean_te_percent": "mean te [% of ‖t‖]",
    "within_2_mm": "te < 2 mm",
    "within_5_mm": "te < 5 mm",
    "within_2_percent": "te < 2 %",
    "within_5_percent": "te < 5 %",
}


def object_points(objects: Mapping[int, Mapping[str, Any]]) -> dict[int, np.ndarray]:
    """Object id -> the points ``(P, 3)`` [mm] the runtime fits to a box (hull points, else box corners)."""
    points_mm = {}
    for obj_id, info in objects.items():
        try:
            points_mm[int(obj_id)] = object_points_mm(info)
        except PopcodeError as error:
            raise PopcodeError(f"object {obj_id}: {error}") from error
    return points_mm


def translations_from_boxes(R_m2c: np.ndarray, instances: Sequence[Instance],
                            points_mm: Mapping[int, np.ndarray]) -> np.ndarray:
    """Translations ``(N, 3)`` [mm] that make each instance, rotated by ``R_m2c (N, 3, 3)``, fill its box.

    The box is the instance's own (the one its crop was taken from), ``K`` its camera's.
    """
    if len(R_m2c) != len(instances):
        raise PopcodeError(f"{len(R_m2c)} rotations for {len(instances)} instances")
    missing = sorted({inst.obj_id for inst in instances} - set(points_mm))
    if missing:
        raise PopcodeError(f"no object points (hull points or 3-D box) for objects {missing}")
    t_mm = np.empty((len(instances), 3))
    for i, (R, inst) in enumerate(zip(R_m2c, instances, strict=True)):
        try:
            t_mm[i] = translation_from_box(R, inst.box, inst.K, points_mm[inst.obj_id])
        except PopcodeError as error:
            raise PopcodeError(f"scene {inst.scene_id}, image {inst.im_id}, object {inst.obj_id}: {error}") from error
    return t_mm


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


def relative_translation_error(t_est_mm: np.ndarray, t_gt_mm: np.ndarray) -> np.ndarray:
    """te divided by the ground-truth distance ``‖t_gt‖``: a fraction, comparable across distances."""
    return translation_error_mm(t_est_mm, t_gt_mm) / np.linalg.norm(np.asarray(t_gt_mm, np.float64), axis=-1)


def translation_summary(t_est_mm: np.ndarray, t_gt_mm: np.ndarray) -> dict[str, float]:
    """Median and mean te [mm] and [% of ‖t_gt‖], and the shares (fractions) within 2 mm and 5 mm (what a gripper
    tolerates) and within 2 % and 5 % of the distance."""
    te_mm = translation_error_mm(t_est_mm, t_gt_mm)
    relative = relative_translation_error(t_est_mm, t_gt_mm)
    if len(te_mm) == 0:
        raise PopcodeError("no translations to summarise")
    return {
        "median_te_mm": float(np.median(te_mm)),
        "mean_te_mm": float(np.mean(te_mm)),
        "median_te_percent": float(100.0 * np.median(relative)),
        "mean_te_percent": float(100.0 * np.mean(relative)),
        "within_2_mm": float(np.mean(te_mm < 2.0)),
        "within_5_mm": float(np.mean(te_mm < 5.0)),
        "within_2_percent": float(np.mean(relative < 0.02)),
        "within_5_percent": float(np.mean(relative < 0.05)),
    }
