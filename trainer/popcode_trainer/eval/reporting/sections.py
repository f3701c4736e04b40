"""The evaluation report's markdown: the paper's tables by pose ambiguity and per object, and the sections a
split or a run adds (visibility bins, detector boxes' IoU, best of the top k, full 6-D poses with or without depth,
confidence, timing). :mod:`.report` writes it with the other files.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT

from ...metrics.recall import METRICS, VISIBILITY_BINS, ambiguous_objects, tightest_thresholds
from ..pipeline.depth_poses import DepthPoses
from ..pipeline.evaluate import MethodResult
from ..pipeline.split import EvalSplit
from ..pipeline.translation import translation_summary
from .confidence import confidence_markdown
from .markdown import markdown_table
from .tables import (
    ambiguity_markdown,
    best_of_top_k_markdown,
    box_iou_markdown,
    per_object_markdown,
    translation_markdown,
    visibility_markdown,
)

GT_ROTATION = "ground-truth rotation"


def timing_markdown(results: Sequence[MethodResult]) -> str:
    """Each method's decoder and model time per crop (crop + network + decoding) beside the metric computation
    time."""
    rows = [(result.name, result.decoder or "–",
             "–" if math.isnan(result.model_ms_per_crop) else f"{result.model_ms_per_crop:.2f}",
             f"{result.metric_s:.1f}") for result in results]
    return markdown_table(["Method", "decoder", "model ms / crop", "metrics s"], rows)


def shared_split(results: Sequence[MethodResult]) -> EvalSplit:
    """The split all results were scored on; results of other instances or thresholds cannot share a table."""
    if not results:
        raise PopcodeError("no results to report")
    split = results[0].split
    for result in results[1:]:
        if [(i.scene_id, i.im_id, i.gt_index) for i in result.split.instances] != [
                (i.scene_id, i.im_id, i.gt_index) for i in split.instances]:
            raise PopcodeError(f"{result.name!r} and {results[0].name!r} were scored on different instances")
        if result.thresholds != results[0].thresholds:
            raise PopcodeError(f"{result.name!r} and {results[0].name!r} were scored with different thresholds")
        if _boxes_of(result.split) != _boxes_of(split):
            raise PopcodeError(f"{result.name!r} and {results[0].name!r} were scored on different boxes "
                               f"({_boxes_of(result.split)} and {_boxes_of(split)})")
    return split


def _boxes_of(split: EvalSplit) -> str:
    boxes = split.detector_boxes
    return "ground-truth boxes" if boxes is None else f"box-noise preset {boxes.preset!r}, seed {boxes.seed}"


def tightest_markdown(results: Sequence[MethodResult]) -> list[str]:
    """The recall at each metric's tightest threshold alone, by pose ambiguity: title, note, tables."""
    first = tightest_thresholds(results[0].thresholds)
    title = (f"## Tightest thresholds (recall): MSSD < {100 * first['mssd_fractions']:g} % of diameter, "
             f"MSPD < {first['mspd_px_at_640']:g} px")
    if any("VSD" in scores for r in results for scores in r.tightest.values()):
        title += f", VSD < {first['vsd_thetas']:g} at tau = {100 * first['vsd_taus']:g} % of diameter"
    note = ("Each metric's tightest threshold alone (the scores above average over all of its thresholds); "
            "MSPD in pixels of a 640 px wide image.")
    return [title, note, ambiguity_markdown({r.name: r.tightest for r in results})]


def report_markdown(results: Sequence[MethodResult]) -> str:
    """Table IV (with / without ambiguity), its tightest-threshold recalls, per-object tables (Table III), each
    method's decoder and timings."""
    split = shared_split(results)
    counts = Counter(inst.obj_id for inst in split.instances)
    ambiguity = ambiguous_objects(split.models_info)
    ambiguous = [obj for obj in split.obj_ids if ambiguity[obj]]
    parts = [
        "## Scores by pose ambiguity (paper Table IV)",
        f"Objects with ambiguity: {ambiguous or 'none'}; instances: {len(split.instances)}.",
        ambiguity_markdown({r.name: r.groups for r in results}),
        *tightest_markdown(results),
        *visibility_section(results),
        *box_iou_section(results),
        *best_of_top_k_section(results),
        "## Scores per object (paper Table III)",
    ]
    present = [m for m in METRICS if any(m in s for r in results for s in r.per_object.values())]
    for metric in present:
        parts.append(per_object_markdown({r.name: r.per_object for r in results}, metric, dict(counts)))
    parts += full_pose_markdown(results)
    confidence = confidence_markdown(results)
    if confidence:
        parts.append(confidence)
    parts += ["## Decoders and timing",
              "The decoder turns a model's output into a rotation (argmax: the paper's; refined: between grid "
              "points, fitted to a population code's peak); – for rotations read from a results file.",
              timing_markdown(results)]
    return "\n\n".join(parts) + "\n"


def visibility_section(results: Sequence[MethodResult]) -> list[str]:
    """Scores per visibility bin: only for a split with occlusion (an instance below the first of VISIBILITY_BINS)."""
    if all(inst.visib_fract >= VISIBILITY_BINS[0][1] for inst in results[0].split.instances):
        return []
    return ["## Scores by visibility (visib_fract of the ground truth)",
            "Occluded instances, and those the image border cuts, binned by the visible fraction of the object; "
            f"instances below {BOP19_MIN_VISIB_FRACT:g} are not evaluated (BOP19).",
            visibility_markdown({r.name: r.by_visibility for r in results})]


def box_iou_section(results: Sequence[MethodResult]) -> list[str]:
    """MSSD per bin of the box IoU: only for a split whose boxes are a detector's."""
    boxes = results[0].split.detector_boxes
    if boxes is None:
        return []
    return ["## MSSD by box IoU",
            f"Each instance cropped from a detector-like box (box-noise preset {boxes.preset!r}, seed {boxes.seed}; "
            f"mean IoU with the ground-truth box {boxes.iou.mean():.3f}), the same box for every method and the "
            "translation fit; binned by that IoU.",
            box_iou_markdown({r.name: r.by_box_iou for r in results})]


def top_k_scores(result: MethodResult) -> dict[int, dict[str, float] | None]:
    """k -> group -> MSSD of the best of the top k, k = 1..top_k; None for k > 1 where the method has no
    hypotheses (k = 1 is its own estimate)."""
    if result.best_of_top_k is not None:
        return dict(result.best_of_top_k.groups)
    return {1: {group: scores["MSSD"] for group, scores in result.groups.items()},
            **dict.fromkeys(range(2, result.top_k + 1))}


def best_of_top_k_section(results: Sequence[MethodResult]) -> list[str]:
    """MSSD of the best of the top-k hypotheses beside the estimate: only when hypotheses were asked for."""
    top_k = max(r.top_k for r in results)
    if top_k == 1:
        return []
    return [f"## MSSD of the best of the top-{top_k} hypotheses",
            "For each instance the candidate of smallest MSSD error among the method's own rotation and the next "
            "distinct poses its population code holds, strongest first (fewer where the code has fewer peaks): "
            "what a robot that can check a few hypotheses gets. A single-output representation has none (–). "
            "Model time per crop includes the hypothesis search.",
            best_of_top_k_markdown({r.name: top_k_scores(r) for r in results}, top_k)]


def depth_row_name(result: MethodResult, posed: DepthPoses) -> str:
    """The table row of a method's poses in one depth mode, e.g. ``population_code, depth + ICP``."""
    return f"{result.name}, {posed.mode.label}"


def translation_rows(results: Sequence[MethodResult]) -> dict[str, dict[str, float]]:
    """Translation-error summaries: per method with its rotation, then with the ground-truth rotation, then from
    depth in each depth mode."""
    rows = {}
    for result in results:
        t_gt = np.stack([inst.t_m2c_mm for inst in result.split.instances])
        if result.full_pose is not None:
            rows[result.name] = translation_summary(result.full_pose.t_est_mm, t_gt)
            rows[f"{result.name}, {GT_ROTATION}"] = translation_summary(result.full_pose.t_gt_rotation_mm, t_gt)
        for posed in result.depth_poses:
            rows[depth_row_name(result, posed)] = translation_summary(posed.t_m2c_mm, t_gt)
    return rows


def six_d_groups(results: Sequence[MethodResult]) -> dict[str, dict[str, dict[str, float]]]:
    """Row -> ambiguity group -> 6-D scores: each method with the box's translation, then in each depth mode."""
    rows = {}
    for result in results:
        if result.full_pose is not None:
            rows[result.name] = result.full_pose.groups
        rows |= {depth_row_name(result, posed): posed.groups for posed in result.depth_poses}
    return rows


def _counts_text(counts: dict[str, int]) -> str:
    return "; ".join(f"{name} {count}" for name, count in counts.items()) or "–"


def depth_step_markdown(results: Sequence[MethodResult]) -> str:
    """Per method and depth mode: where the translations came from, why depth was not used, and its cost."""
    rows = [[depth_row_name(r, posed), _counts_text(posed.source_counts()), _counts_text(posed.note_counts()),
             f"{1000.0 * posed.depth_s.mean():.2f}", f"{1000.0 * np.percentile(posed.depth_s, 90):.2f}"]
            for r in results for posed in r.depth_poses]
    return markdown_table(["Method, depth", "translation from", "why not (fully) from depth",
                           "depth ms / instance", "p90 ms"], rows)


def full_pose_markdown(results: Sequence[MethodResult]) -> list[str]:
    """The translation-error table and the 6-D scores by ambiguity (with depth, its rows and the depth step's
    sources and cost); nothing without full poses."""
    posed = [r for r in results if r.full_pose is not None]
    if not posed:
        return []
    with_depth = any(r.depth_poses for r in posed)
    parts = [
        "## Full 6-D pose: translation from the box" + (" and from depth" if with_depth else ""),
        "The translation is fitted to each instance's box (the one it was cropped with) as the runtime does "
        f"it, with the method's rotation and, to show the box fit alone, with the {GT_ROTATION}. "
        "te is the distance to the true translation; % of the true distance ‖t‖.",
    ]
    if with_depth:
        parts.append(
            "Rows \"depth\": each instance placed as `popcode run --depth` places it, along the box's ray at the "
            "distance its depth image measures; \"depth + ICP\": as `--depth --refine`, rotation and translation "
            "refined against the observed points (small_gicp), kept where it fits the depth better. An instance "
            "whose depth is unusable keeps the box's translation (counted below, with the runtime's reason).")
    parts += [
        translation_markdown(translation_rows(posed)),
        "**6-D scores** (rotation and translation estimated)",
        ambiguity_markdown(six_d_groups(posed)),
    ]
    if with_depth:
        parts += ["**Depth step**: each translation's source, the runtime's reasons where depth was not (fully) "
                  "used, and the milliseconds per instance of the depth step (the box fit it starts from, the "
                  "depth's translation and, refining, GICP; numpy and small_gicp on one thread, slowed by busy "
                  "onnxruntime threads beside it: `--threads 1` times it as on one core): the mean, and the 90th "
                  "percentile of each image's mean.",
                  depth_step_markdown(posed)]
    return parts
