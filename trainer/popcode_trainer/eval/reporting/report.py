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
import re
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.bop.bop19_csv import PoseEstimate, write_bop19_results

from ...metrics.confidence import rotation_errors_deg
from ...metrics.pose_errors import rotation_error_deg, translation_error_mm
from ...metrics.recall import (
    InstanceErrors,
    Thresholds,
    tightest_thresholds,
)
from ..pipeline.estimates import UNKNOWN_TIME_S
from ..pipeline.evaluate import MethodResult
from ..pipeline.translation import relative_translation_error
from .confidence import RELIABILITY_PNG, plot_reliability
from .sections import GT_ROTATION, depth_row_name, report_markdown, shared_split, translation_rows
from .tables import (
    to_json,
)

ERRORS_CSV = "errors_{name}.csv"
BOP19_CSV = "{name}_bop19.csv"
BOP19_6D_CSV = "{name}_6d_bop19.csv"
BOP19_DEPTH_CSV = "{name}_6d_{mode}_bop19.csv"
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


def report_dict(results: Sequence[MethodResult]) -> dict[str, Any]:
    """The JSON report: per method its models and their decoder (None: a results file), per-object and grouped
    scores, tightest recalls and timings."""
    split = shared_split(results)
    translation = translation_rows(results)
    methods: dict[str, Any] = {}
    for r in results:
        methods[r.name] = {"models": list(r.model_paths), "decoder": r.decoder, "groups": r.groups,
                           "per_object": r.per_object,
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
    decoding, not reading the image). Given rotations know neither: score 1, time -1. An instance a results file
    has no estimate of (NaN rotation) has no line."""
    count = len(result.split.instances)
    score = np.ones(count) if result.score is None else result.score
    image_s = np.full(count, UNKNOWN_TIME_S) if result.image_s is None else result.image_s
    R_m2c = result.R_est if R_m2c is None else R_m2c
    return [PoseEstimate(inst.scene_id, inst.im_id, inst.obj_id, float(score[i]), R_m2c[i], t_m2c_mm[i],
                         float(image_s[i]))
            for i, inst in enumerate(result.split.instances) if np.isfinite(R_m2c[i]).all()]


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
