"""Evaluation results -> files: per-instance errors (CSV), the paper's tables (markdown, JSON), BOP19 CSV.

With full 6-D poses (translation from the box) each file gains them beside the
rotation-only results: error columns suffixed ``_6d``, a translation-error
table and the 6-D scores, a second BOP19 file. With depth, each depth mode
(``depth``, ``refined``) adds its rows to those tables, its columns (suffixed
``_depth`` / ``_refined``) and BOP19 file, and a table of where the translations
came from and what the depth step cost. With a detector's boxes each
instance's ``box_iou`` and a table of MSSD by box IoU; with hypotheses
(``top_k > 1``) the MSSD of the best of the top k.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.bop.bop19_csv import PoseEstimate, write_bop19_results
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT

from ...metrics.confidence import rotation_errors_deg
from ...metrics.pose_errors import rotation_error_deg, translation_error_mm
from ...metrics.recall import (
    METRICS,
    VISIBILITY_BINS,
    InstanceErrors,
    Thresholds,
    ambiguous_objects,
    tightest_thresholds,
)
from ..pipeline.depth_poses import DepthPoses
from ..pipeline.estimates import UNKNOWN_TIME_S
from ..pipeline.evaluate import MethodResult
from ..pipeline.split import EvalSplit
from ..pipeline.translation import relative_translation_error, translation_summary
from .confidence import RELIABILITY_PNG, confidence_markdown, plot_reliability
from .markdown import markdown_table
from .tables import (
    ambiguity_markdown,
    best_of_top_k_markdown,
    box_iou_markdown,
    per_object_markdown,
    to_json,
    translation_markdown,
    visibility_markdown,
)

ERRORS_CSV = "errors_{name}.csv"
BOP19_CSV = "{name}_bop19.csv"
BOP19_6D_CSV = "{name}_6d_bop19.csv"
BOP19_DEPTH_CSV = "{name}_6d_{mode}_bop19.csv"
GT_ROTATION = "ground-truth rotation"
REPORT_MD = "report.md"
REPORT_JSON = "report.json"


def file_stem(name: str) -> str:
    """A method name made safe for a file name."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("_") or "method"


def _error_columns(errors: InstanceErrors, i: int, thresholds: Thresholds, suffix: str = "") -> dict[str, float]:
    """Instance ``i``'s errors by column name (depth errors when computed), each name ending in ``suffix``."""
    columns = {"mssd_mm": errors.mssd_mm[i], "mspd_px": errors.mspd_px[i], "adi_mm": errors.adi_mm[i]}
    if errors.vsd is not None:
        for tau, value in zip(thresholds.vsd_taus, errors.vsd[i], strict=True):
            columns[f"vsd_tau{tau:.2f}"] = value
        columns[f"vsd_tau{thresholds.vsd_single_tau_mm:g}mm"] = errors.vsd_single_tau[i]
        columns["vss"] = errors.vss[i]
    return {name + suffix: float(value) for name, value in columns.items()}


def instance_rows(result: MethodResult, thresholds: Thresholds) -> list[dict[str, Any]]:
    """One row per ground-truth instance: its ids and every error; with full poses also te and the 6-D errors.

    ``re_deg`` is the raw rotation angle between estimate and ground truth (BOP's
    re); ``re_sym_deg`` the same up to the object's symmetries (the smallest over
    its equivalent poses; the axis angle for a continuous symmetry), never larger;
    where a part of the split nearly has a symmetry it does not declare,
    ``re_look_alike_deg`` up to its look-alike poses too (the error an estimate
    that cannot see the feature breaking the symmetry is held to).
    """
    split, pose = result.split, result.full_pose
    R_gt = np.stack([inst.R_m2c for inst in split.instances])
    t_gt = np.stack([inst.t_m2c_mm for inst in split.instances])
    re_deg = rotation_error_deg(result.R_est, R_gt)
    re_sym_deg = rotation_errors_deg(result.R_est, R_gt, result.errors.obj_id, split.models_info)
    up_to = {"re_sym_deg": re_sym_deg}
    if result.look_alikes:
        up_to["re_look_alike_deg"] = rotation_errors_deg(result.R_est, R_gt, result.errors.obj_id,
                                                         split.models_info, result.look_alikes)
    te = {} if pose is None else {
        name: (translation_error_mm(t, t_gt), relative_translation_error(t, t_gt))
        for name, t in (("te", pose.t_est_mm), ("te_gt_rotation", pose.t_gt_rotation_mm))
    }
    depth_te = [(posed, translation_error_mm(posed.t_m2c_mm, t_gt), relative_translation_error(posed.t_m2c_mm, t_gt))
                for posed in result.depth_poses]
    rows = []
    for i, inst in enumerate(split.instances):
        row: dict[str, Any] = {
            "scene_id": inst.scene_id, "im_id": inst.im_id, "obj_id": inst.obj_id, "gt_index": inst.gt_index}
        if split.detector_boxes is not None:
            row["box_iou"] = float(split.detector_boxes.iou[i])
        row |= {"re_deg": float(re_deg[i]), **{name: float(values[i]) for name, values in up_to.items()},
                **_error_columns(result.errors, i, thresholds)}
        if result.best_of_top_k is not None:
            row[f"mssd_mm_best_of_top{result.top_k}"] = float(result.best_of_top_k.mssd_mm[-1, i])
        for name, (mm, fraction) in te.items():
            row[f"{name}_mm"], row[f"{name}_percent"] = float(mm[i]), 100.0 * float(fraction[i])
        if pose is not None:
            row |= _error_columns(pose.errors, i, thresholds, "_6d")
        for posed, mm, fraction in depth_te:
            key = posed.mode.key
            row |= {f"te_{key}_mm": float(mm[i]), f"te_{key}_percent": 100.0 * float(fraction[i]),
                    f"t_source_{key}": posed.sources[i], f"depth_note_{key}": posed.notes[i] or "",
                    **_error_columns(posed.errors, i, thresholds, f"_6d_{key}")}
        rows.append(row)
    return rows


def write_instance_errors(path: Path, rows: Sequence[dict[str, Any]]) -> Path:
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=list(rows[0]))
    writer.writeheader()
    writer.writerows(rows)
    write_bytes_atomic(path, text.getvalue().encode())
    return path


def report_files(names: Sequence[str], bop19_csv: bool = False, depth_keys: Sequence[str] = ()) -> list[str]:
    """Every file :func:`write_report` may write for the methods ``names`` (with ``bop19_csv``: the 6-D and the
    ``depth_keys`` CSVs too), so that a command checks them before any work; two names that make one file are
    refused."""
    stems: dict[str, str] = {}
    for name in names:
        other = stems.setdefault(file_stem(name), name)
        if other != name:
            raise PopcodeError(f"methods {other!r} and {name!r} would write the same files ({file_stem(name)}); "
                               "give them names that differ in letters or digits (--name)")
    files = {REPORT_MD: "the report", REPORT_JSON: "the report", RELIABILITY_PNG: "the report"}
    for stem, name in stems.items():
        kinds = [ERRORS_CSV] + ([BOP19_CSV, BOP19_6D_CSV] if bop19_csv else [])
        planned = [kind.format(name=stem) for kind in kinds]
        planned += [BOP19_DEPTH_CSV.format(name=stem, mode=key) for key in depth_keys] if bop19_csv else []
        for file_name in planned:
            other = files.setdefault(file_name, name)
            if other != name:
                raise PopcodeError(f"{file_name} would be written for {other!r} and for {name!r}; give the methods "
                                   "names that do not make one another's file names (--name)")
    return list(files)


def timing_markdown(results: Sequence[MethodResult]) -> str:
    """Model time per crop (crop + network + decoding) beside the metric computation time."""
    rows = [(result.name, "–" if math.isnan(result.model_ms_per_crop) else f"{result.model_ms_per_crop:.2f}",
             f"{result.metric_s:.1f}") for result in results]
    return markdown_table(["Method", "model ms / crop", "metrics s"], rows)


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
    """Table IV (with / without ambiguity), its tightest-threshold recalls, per-object tables (Table III), timings."""
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
    parts += ["## Timing", timing_markdown(results)]
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


def report_dict(results: Sequence[MethodResult]) -> dict[str, Any]:
    """The JSON report: per method its models, per-object and grouped scores, tightest recalls and timings."""
    split = shared_split(results)
    translation = translation_rows(results)
    methods: dict[str, Any] = {}
    for r in results:
        methods[r.name] = {"models": list(r.model_paths), "groups": r.groups, "per_object": r.per_object,
                           "tightest": r.tightest, "by_visibility": r.by_visibility,
                           "model_ms_per_crop": r.model_ms_per_crop, "metric_s": r.metric_s,
                           "confidence": None if r.confidence is None else r.confidence.to_dict()}
        if r.split.detector_boxes is not None:
            methods[r.name]["by_box_iou"] = r.by_box_iou
        if r.top_k > 1:
            methods[r.name]["best_of_top_k"] = None if r.best_of_top_k is None else r.best_of_top_k.groups
        if r.full_pose is not None:
            methods[r.name]["full_pose"] = {
                "translation": translation[r.name], "translation_gt_rotation": translation[f"{r.name}, {GT_ROTATION}"],
                "groups": r.full_pose.groups, "per_object": r.full_pose.per_object,
            }
        if r.depth_poses:
            methods[r.name]["depth"] = {posed.mode.key: {
                "translation": translation[depth_row_name(r, posed)], "groups": posed.groups,
                "per_object": posed.per_object, "sources": posed.source_counts(), "notes": posed.note_counts(),
                "depth_ms_per_instance": 1000.0 * float(posed.depth_s.mean()),
            } for posed in r.depth_poses}
    report: dict[str, Any] = {"instances_per_object": dict(Counter(inst.obj_id for inst in split.instances)),
                              "tightest_thresholds": tightest_thresholds(results[0].thresholds)}
    boxes = split.detector_boxes
    if boxes is not None:
        report["box_noise"] = {"preset": boxes.preset, "seed": boxes.seed, "mean_iou": float(boxes.iou.mean())}
    return report | {"methods": methods}


def bop19_estimates(result: MethodResult, t_m2c_mm: Sequence[np.ndarray],
                    R_m2c: np.ndarray | None = None) -> list[PoseEstimate]:
    """The method's estimates as BOP19 results lines, with the given translations (and rotations, default the
    method's own, e.g. refined against depth): ``score`` the calibrated
    confidence (the raw score for a model without a calibrator, the file's for a results file), ``time`` the
    seconds of the method's estimates of the instance's image, the same on each of its rows (crop, network and
    decoding, not reading the image). Given rotations know neither: score 1, time -1."""
    count = len(result.split.instances)
    score = np.ones(count) if result.score is None else result.score
    image_s = np.full(count, UNKNOWN_TIME_S) if result.image_s is None else result.image_s
    R_m2c = result.R_est if R_m2c is None else R_m2c
    return [PoseEstimate(inst.scene_id, inst.im_id, inst.obj_id, float(score[i]), R_m2c[i], t_m2c_mm[i],
                         float(image_s[i]))
            for i, inst in enumerate(result.split.instances)]


def write_report(results: Sequence[MethodResult], out_dir: str | Path,
                 thresholds: Thresholds | None = None, bop19_csv: bool = False) -> list[Path]:
    """Write every file of an evaluation into ``out_dir``; returns their paths."""
    split = shared_split(results)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    thresholds = thresholds or Thresholds()
    written = []
    for result in results:
        stem = file_stem(result.name)
        written.append(write_instance_errors(out_dir / ERRORS_CSV.format(name=stem),
                                             instance_rows(result, thresholds)))
        if not bop19_csv:
            continue
        t_gt = [inst.t_m2c_mm for inst in split.instances]
        files = [(BOP19_CSV.format(name=stem), t_gt, None)]
        if result.full_pose is not None:
            files.append((BOP19_6D_CSV.format(name=stem), list(result.full_pose.t_est_mm), None))
        files += [(BOP19_DEPTH_CSV.format(name=stem, mode=posed.mode.key), list(posed.t_m2c_mm), posed.R_m2c)
                  for posed in result.depth_poses]
        for file_name, translations, rotations in files:
            path = out_dir / file_name
            write_bop19_results(path, bop19_estimates(result, translations, rotations))
            written.append(path)
    reliability = plot_reliability(results, out_dir / RELIABILITY_PNG)
    if reliability is not None:
        written.append(reliability)
    write_bytes_atomic(out_dir / REPORT_MD, report_markdown(results).encode())
    write_bytes_atomic(out_dir / REPORT_JSON, (to_json(report_dict(results)) + "\n").encode())
    return [*written, out_dir / REPORT_MD, out_dir / REPORT_JSON]
