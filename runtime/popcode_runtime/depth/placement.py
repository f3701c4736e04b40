"""One instance's pose with a depth image: the box's translation, then the depth's, then (asked) the refined pose.

Each step falls back to the one before it, and says why: depth that cannot
place the instance leaves the box's translation (:func:`.surface_fit.translation_from_depth`),
a refinement that fails or fits the depth worse leaves the depth's
(:func:`.icp.refine_pose`). With several starting rotations (the
code's hypotheses) each is placed and the pose the depth confirms best kept.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..geometry.translation import translation_from_box
from .icp import refine_pose
from .surface_fit import ObjectSurface, TranslationSource, depth_fit, has_readings, translation_from_depth


@dataclass(frozen=True)
class DepthPose:
    """One instance's pose with depth, where its translation came from, and why depth was not (fully) used."""

    R_m2c: np.ndarray  # (3, 3); changed only by refinement
    t_m2c_mm: np.ndarray  # (3,)
    source: TranslationSource
    fit: float | None  # depth_fit of the pose; None when depth could not place it
    note: str | None  # why the translation is from the box, or why refinement was not kept; None when all went well


def pose_with_depth(starts: Sequence[np.ndarray], box: Sequence[float], K: np.ndarray, depth_mm: np.ndarray,
                    surface: ObjectSurface, hull_points_mm: np.ndarray, info: Mapping[str, Any],
                    refine: bool = False) -> DepthPose:
    """The pose of the object in ``box`` from its rotation ``starts[0]`` and the depth image.

    The translation comes from the depth along the box's ray; where the depth
    cannot place the object it is the box's, with the reason in ``note``.
    ``refine``: rotation and translation refined against the observed points
    from every rotation in ``starts`` (the code's hypotheses), the best fit
    kept; a refinement that fits the depth worse than its start is dropped.
    ``info`` is the object's metadata entry (its symmetries keep the refinement
    inside the object's symmetry class).
    """
    first = np.asarray(starts[0], dtype=np.float64)
    if not has_readings(depth_mm, box):
        return DepthPose(first, translation_from_box(first, box, K, hull_points_mm), TranslationSource.BOX, None,
                         "no valid depth in the box")
    best = _place(first, box, K, depth_mm, surface, hull_points_mm, info, refine)
    for R in starts[1:] if refine else ():
        candidate = _place(np.asarray(R, dtype=np.float64), box, K, depth_mm, surface, hull_points_mm, info, refine)
        if candidate.fit is not None and (best.fit is None or candidate.fit > best.fit):
            best = candidate
    return best


def _place(R: np.ndarray, box: Sequence[float], K: np.ndarray, depth_mm: np.ndarray, surface: ObjectSurface,
           hull_points_mm: np.ndarray, info: Mapping[str, Any], refine: bool) -> DepthPose:
    """One start: the box's translation, then the depth's, then (``refine``) the refined pose if it fits better."""
    t_box = translation_from_box(R, box, K, hull_points_mm)
    t_depth, problem = translation_from_depth(R, t_box, K, depth_mm, surface)
    if t_depth is None:
        return DepthPose(R, t_box, TranslationSource.BOX, None, problem)
    start_fit = depth_fit(R, t_depth, K, depth_mm, surface)
    if not refine:
        return DepthPose(R, t_depth, TranslationSource.DEPTH, start_fit, None)
    refined, problem = refine_pose(R, t_depth, K, depth_mm, box, surface, info)
    if refined is None:
        return DepthPose(R, t_depth, TranslationSource.DEPTH, start_fit, problem)
    R_refined, t_refined = refined
    fit = depth_fit(R_refined, t_refined, K, depth_mm, surface)
    if fit < start_fit:
        return DepthPose(R, t_depth, TranslationSource.DEPTH, start_fit, f"refinement fitted the depth worse: "
                         f"{fit:.2f} < {start_fit:.2f}, kept the depth translation")
    return DepthPose(R_refined, t_refined, TranslationSource.REFINED, fit, None)
