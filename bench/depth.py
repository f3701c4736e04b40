"""6-D poses with depth: box vs depth vs depth + ICP on a clean and a cluttered rendered split, against issue 29.

    python -m bench.depth [--quick] [--images 10] [--clean-seed 6101] [--scenes 12] [--seed 6102]
        [--size 720 540] [--sensor industrial]
        [--models models/builtin-parts-1-2.onnx models/builtin-parts-3-6.onnx] [--out bench/results]

Renders two splits of the built-in parts with seeds no training, test or demo run uses: a clean one (one
part per image at a random position, ``popcode-train render --images N --random-position``) and a
cluttered bin (``popcode-train render --scenes N --sensor industrial``, the sensor's depth noise included).
On each, the models are scored through the evaluation with depth and refinement
(:func:`popcode_trainer.eval.pipeline.evaluate.evaluate_models`: exactly what ``popcode-train evaluate
--depth --refine --threads 1`` reports): the translation from the box, from depth, and depth followed by
GICP refinement of rotation and translation, each as 6-D scores beside the rotation-only protocol, with the
instances that fell back to the box and the depth step's milliseconds per instance (models on one
onnxruntime thread: idle worker threads spinning beside it would slow the depth step). Rows from the
ground-truth rotation place each instance with the runtime's functions directly, each step timed alone:
the floor of each method. The goals table checks issue 29's goals.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.depth.placement import pose_with_depth
from popcode_runtime.depth.surface_fit import TranslationSource, check_depth, object_surface, read_depth
from popcode_runtime.geometry.translation import object_points_mm, translation_from_box
from popcode_trainer.data.bop import Instance
from popcode_trainer.data.hull import with_hull_points
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.eval.pipeline.depth_poses import DEPTH, REFINED, note_kind
from popcode_trainer.eval.pipeline.evaluate import MethodResult, evaluate_models
from popcode_trainer.eval.pipeline.models import Method, load_model
from popcode_trainer.eval.pipeline.split import EvalSplit, read_eval_split
from popcode_trainer.eval.pipeline.translation import translation_summary
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.confidence import rotation_errors_deg
from tools.command import run_command
from tools.paths import RESULTS, ROOT, SHIPPED_MODELS
from tools.report import machine, machine_line, write_results

METHOD = "shipped models"
BOX = "box"
MODES = (BOX, DEPTH.label, REFINED.label)
CLEAN_SEED, CLUTTER_SEED = 6101, 6102  # no training, test or demo render uses these
# Issue 29's goals
MAX_MEDIAN_TE_MM, MAX_MEDIAN_TE_PERCENT = 1.0, 0.5  # in clutter, with depth
MIN_REFINEMENT_GAIN = 0.05  # 6-D MSSD of depth + ICP over depth alone, in clutter
MAX_DEPTH_MS = 5.0  # the depth step per instance, one core


@dataclasses.dataclass(frozen=True)
class Poses:
    """One row's poses, instance by instance, where each translation came from, and the seconds of each (None:
    not timed on its own)."""

    R_m2c: np.ndarray  # (N, 3, 3)
    t_m2c_mm: np.ndarray  # (N, 3)
    sources: list[str]
    seconds: np.ndarray | None
    cpu_seconds: np.ndarray | None = None  # the thread's CPU time: the cost on one core, whatever the machine's load


def source_text(source: str, note: str | None) -> str:
    """A translation's source and the kind of its note, for counting."""
    return source if note is None else f"{source} ({note_kind(note)})"


def true_rotation_rows(instances: Sequence[Instance], objects: Mapping[int, dict[str, Any]]) -> dict[str, Poses]:
    """Each method from the ground-truth rotation with the runtime's functions, each step timed alone."""
    depths: dict[Path, np.ndarray] = {}
    found: dict[str, list[tuple[np.ndarray, np.ndarray, str, float, float]]] = {mode: [] for mode in MODES}
    for inst in instances:
        if inst.depth_path not in depths:
            raw = read_depth(inst.depth_path)
            depths[inst.depth_path] = check_depth(raw, raw.shape, inst.depth_scale)
        info = objects[inst.obj_id]
        surface, hull = object_surface(info), object_points_mm(info)
        started, cpu_started = time.perf_counter(), time.thread_time()
        t_box = translation_from_box(inst.R_m2c, inst.box, inst.K, hull)
        found[BOX].append((inst.R_m2c, t_box, TranslationSource.BOX, time.perf_counter() - started,
                           time.thread_time() - cpu_started))
        for mode, refine in ((DEPTH.label, False), (REFINED.label, True)):
            started, cpu_started = time.perf_counter(), time.thread_time()
            pose = pose_with_depth([inst.R_m2c], inst.box, inst.K, depths[inst.depth_path], surface, hull, info,
                                   refine)
            found[mode].append((pose.R_m2c, pose.t_m2c_mm, source_text(pose.source, pose.note),
                                time.perf_counter() - started, time.thread_time() - cpu_started))
    return {mode: Poses(np.stack([r[0] for r in rows]), np.stack([r[1] for r in rows]), [r[2] for r in rows],
                        np.array([r[3] for r in rows]), np.array([r[4] for r in rows]))
            for mode, rows in found.items()}


def model_rows(result: MethodResult) -> dict[str, Poses]:
    """The evaluation's poses: the box's translation (timed within the models' decoding), then each depth mode."""
    rows = {BOX: Poses(result.R_est, result.full_pose.t_est_mm, [TranslationSource.BOX] * len(result.R_est), None)}
    for posed in result.depth_poses:
        rows[posed.mode.label] = Poses(posed.R_m2c, posed.t_m2c_mm, [source_text(s, n) for s, n in
                                                                     zip(posed.sources, posed.notes, strict=True)],
                                       posed.depth_s)
    return rows


def row_summary(poses: Poses, split: EvalSplit) -> dict[str, Any]:
    """Translation and rotation errors of one row, its sources and its milliseconds per instance."""
    instances = split.instances
    R_gt = np.stack([inst.R_m2c for inst in instances])
    obj_ids = np.array([inst.obj_id for inst in instances])
    rotation_deg = rotation_errors_deg(poses.R_m2c, R_gt, obj_ids, split.models_info)
    timed = poses.seconds is not None
    return {
        **translation_summary(poses.t_m2c_mm, np.stack([inst.t_m2c_mm for inst in instances])),
        "median_rotation_error_deg": float(np.median(rotation_deg)),
        "rotation_within_5_deg": float(np.mean(rotation_deg < 5.0)),
        "sources": dict(Counter(poses.sources).most_common()),
        "mean_ms": float(1000.0 * np.mean(poses.seconds)) if timed else None,
        "p90_ms": float(1000.0 * np.percentile(poses.seconds, 90)) if timed else None,
        "mean_cpu_ms": None if poses.cpu_seconds is None else float(1000.0 * np.mean(poses.cpu_seconds)),
    }


def score_split(split_dir: Path, models: Sequence[Path]) -> dict[str, Any]:
    """Every row of one split, the 6-D scores (all objects) and the split's facts."""
    split = read_eval_split([split_dir], split_dir / BUILTIN_MODELS_FOLDER)
    objects = with_hull_points(split.models_info, split.models_dir)
    method = Method(METHOD, tuple(load_model(path, threads=1) for path in models))
    result = evaluate_models([method], split, translation=True, depth=True, refine=True)[0]
    rows = {f"ground-truth rotation, {mode}": row_summary(poses, split)
            for mode, poses in true_rotation_rows(split.instances, objects).items()}
    rows |= {f"model rotation, {mode}": row_summary(poses, split) for mode, poses in model_rows(result).items()}
    scores = {"rotation only, true translation": result.groups["All objects"],
              BOX: result.full_pose.groups["All objects"]}
    scores |= {posed.mode.label: posed.groups["All objects"] for posed in result.depth_poses}
    distance_mm = np.linalg.norm(np.stack([inst.t_m2c_mm for inst in split.instances]), axis=1)
    return {"instances": len(split.instances), "images": len({inst.image_path for inst in split.instances}),
            "distance_mm_min_median_max": [float(distance_mm.min()), float(np.median(distance_mm)),
                                           float(distance_mm.max())],
            "rows": rows, "scores_all_objects": scores}


def goals(splits: Mapping[str, Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Issue 29's goals with this run's numbers: met or missed."""
    found = []
    clutter = splits["cluttered"]
    for mode in (DEPTH.label, REFINED.label):
        row = clutter["rows"][f"model rotation, {mode}"]
        found.append({"goal": f"median te in clutter < {MAX_MEDIAN_TE_MM:g} mm and < {MAX_MEDIAN_TE_PERCENT:g} % "
                              f"of the distance ({mode})",
                      "value": f"{row['median_te_mm']:.2f} mm, {row['median_te_percent']:.2f} %",
                      "met": row["median_te_mm"] < MAX_MEDIAN_TE_MM
                      and row["median_te_percent"] < MAX_MEDIAN_TE_PERCENT})
    for name, split in splits.items():
        scores = split["scores_all_objects"]
        rotation_only = scores["rotation only, true translation"]["MSSD"]
        for mode in (DEPTH.label, REFINED.label):
            found.append({"goal": f"6-D MSSD ({mode}) ≥ rotation-only MSSD with the true translation, {name}",
                          "value": f"{100 * scores[mode]['MSSD']:.1f} % vs {100 * rotation_only:.1f} %",
                          "met": scores[mode]["MSSD"] >= rotation_only})
    gain = clutter["scores_all_objects"][REFINED.label]["MSSD"] - clutter["scores_all_objects"][DEPTH.label]["MSSD"]
    found.append({"goal": f"refinement adds ≥ {100 * MIN_REFINEMENT_GAIN:g} points of 6-D MSSD in clutter",
                  "value": f"{100 * gain:+.1f} points", "met": gain >= MIN_REFINEMENT_GAIN})
    for mode in (DEPTH.label, REFINED.label):
        ms = {name: split["rows"][f"model rotation, {mode}"]["mean_ms"] for name, split in splits.items()}
        cpu = {name: split["rows"][f"ground-truth rotation, {mode}"]["mean_cpu_ms"] for name, split in splits.items()}
        step = "the depth step (box fit + translation from depth)" if mode == DEPTH.label else \
            "the depth step with the optional refinement"
        found.append({"goal": f"{step} ≤ {MAX_DEPTH_MS:g} ms per instance on one core",
                      "value": ", ".join(f"{value:.2f} ms {name}" for name, value in ms.items())
                      + " (model rows, wall); CPU time from the true rotation: "
                      + ", ".join(f"{value:.2f} ms {name}" for name, value in cpu.items()),
                      "met": max(ms.values()) <= MAX_DEPTH_MS})
    return found


def split_markdown(name: str, split: Mapping[str, Any], description: str) -> str:
    low, median, high = split["distance_mm_min_median_max"]
    header = ["Rotation, translation", "median te [mm]", "median te [% of ‖t‖]", "te < 2 mm", "te < 5 mm",
              "median re [°]", "re < 5°", "ms / instance (mean, p90)", "CPU ms (mean)", "translation from"]
    rows = []
    for row_name, row in split["rows"].items():
        ms = "" if row["mean_ms"] is None else f"{row['mean_ms']:.2f}, {row['p90_ms']:.2f}"
        cpu = "" if row["mean_cpu_ms"] is None else f"{row['mean_cpu_ms']:.2f}"
        sources = "; ".join(f"{source} {count}" for source, count in row["sources"].items())
        rows.append([row_name, f"{row['median_te_mm']:.2f}", f"{row['median_te_percent']:.2f}",
                     f"{100 * row['within_2_mm']:.0f} %", f"{100 * row['within_5_mm']:.0f} %",
                     f"{row['median_rotation_error_deg']:.2f}", f"{100 * row['rotation_within_5_deg']:.0f} %", ms,
                     cpu, sources])
    scores = [[row_name, *(f"{100 * values[metric]:.1f} %" for metric in ("MSSD", "MSPD", "VSD"))]
              for row_name, values in split["scores_all_objects"].items()]
    return "\n\n".join([
        f"## {name.capitalize()} split",
        f"{description}; {split['instances']} instances at least 10 % visible in {split['images']} images, distance "
        f"{low:.0f}–{high:.0f} mm (median {median:.0f}); ground-truth boxes (`bbox_obj`).",
        markdown_table(header, rows),
        "**6-D scores, all objects** (model rotation; the first row is the paper's protocol)",
        markdown_table(["Translation", "MSSD", "MSPD", "VSD"], scores),
    ])


def to_markdown(payload: Mapping[str, Any], commands: Sequence[str]) -> str:
    settings = payload["settings"]
    found = payload["goals"]
    load, cores = payload["machine"]["load_average_1m"], payload["machine"]["cores"]
    return "\n\n".join([
        "# 6-D poses with depth: box vs depth vs depth + ICP (issue 29)",
        machine_line(payload["machine"]),
        "Command: `" + commands[0] + "`; the same through the command line:\n\n```bash\n"
        + "\n".join(commands[1:]) + "\n```",
        f"Models: {', '.join(Path(m).name for m in settings['models'])} (one onnxruntime thread). te: translation "
        "error; re: rotation error up to symmetry (the axis alone for a continuous symmetry). \"depth\": the "
        "translation along the box's ray at the distance the depth measures; \"depth + ICP\": then rotation and "
        "translation refined by GICP (small_gicp), kept where it fits the depth better. Milliseconds per "
        "instance: ground-truth rows time each step alone (box = the box fit; depth = box fit + depth; depth + "
        "ICP = box fit + depth + GICP), in wall time and in the thread's CPU time (the cost on one core whatever "
        "the machine's load); model rows time the runtime's depth step (`Timings.depth_s`: the same steps from "
        "the model's rotation, wall time). The timing goal is judged on the model rows. \"translation from\": "
        "where each translation came from, with the runtime's reason where depth was not (fully) used.",
        *(split_markdown(name, split, settings["splits"][name]) for name, split in payload["splits"].items()),
        "## Issue 29's goals",
        markdown_table(["goal", "this run", ""], [[g["goal"], g["value"], "met" if g["met"] else "**missed**"]
                                                  for g in found]),
        f"The timing goal is judged on wall time, which on this machine (load {load:.1f} on {cores} cores) includes "
        "waiting for a core; the CPU time is what the step costs one core.",
    ])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="2 images per part, 3 scenes at 360x270 (a smoke run)")
    parser.add_argument("--images", type=int, default=10, help="clean split: images per part (default 10)")
    parser.add_argument("--clean-seed", type=int, default=CLEAN_SEED)
    parser.add_argument("--scenes", type=int, default=12, help="cluttered split: scene images (default 12)")
    parser.add_argument("--seed", type=int, default=CLUTTER_SEED, help="cluttered split's seed")
    parser.add_argument("--size", type=int, nargs=2, default=(720, 540), metavar=("W", "H"),
                        help="cluttered split's image size (default 720 540)")
    parser.add_argument("--sensor", default="industrial", help="cluttered split's sensor preset (default industrial)")
    parser.add_argument("--models", type=Path, nargs="+", default=list(SHIPPED_MODELS))
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    images, scenes, size = (2, 3, (360, 270)) if args.quick else (args.images, args.scenes, tuple(args.size))
    work = args.out / ("depth-work-quick" if args.quick else "depth-work")
    try:  # the splits are kept in `work` and reused; one an older renderer wrote is refused
        clean = render_builtin_split(work / f"clean-{images}-{args.clean_seed}", images, seed=args.clean_seed,
                                     random_position=True, progress=True)
        clutter = render_cluttered_test_split(work / f"clutter-{scenes}x{size[0]}-{args.sensor}-{args.seed}",
                                              scenes=scenes, size=size, seed=args.seed, sensor=args.sensor,
                                              progress=True)
    except PopcodeError as error:
        parser.exit(2, f"bench.depth: {error} (delete {work} to render the splits again)\n")
    descriptions = {"clean": f"one part per 128×128 image at a random position, {images} images per part, seed "
                             f"{args.clean_seed}",
                    "cluttered": f"{scenes} bin scenes at {size[0]}×{size[1]} px, sensor `{args.sensor}` (its depth "
                                 f"noise included), seed {args.seed}"}
    splits = {name: score_split(folder, args.models) for name, folder in (("clean", clean), ("cluttered", clutter))}
    payload = {"machine": machine(), "settings": {"splits": descriptions, "models": [str(p) for p in args.models]},
               "splits": splits, "goals": goals(splits)}
    models = " ".join(str(path.resolve().relative_to(ROOT)) if path.resolve().is_relative_to(ROOT) else str(path)
                      for path in args.models)
    commands = [
        "python -m bench.depth" + (" --quick" if args.quick else
                                   f" --images {images} --clean-seed {args.clean_seed} --scenes {scenes} --seed "
                                   f"{args.seed} --size {size[0]} {size[1]} --sensor {args.sensor}"),
        f"popcode-train render --images {images} --objects builtin --seed {args.clean_seed} --random-position "
        "--out clean",
        f"popcode-train render --scenes {scenes} --objects builtin --size {size[0]} {size[1]} --sensor {args.sensor} "
        f"--seed {args.seed} --out clutter",
        *(f"popcode-train evaluate {models} {' '.join(['--name shipped'] * len(args.models))} --split {name} "
          f"--models-dir {name}/models --translation --depth --refine --threads 1 --out eval-{name}"
          for name in ("clean", "clutter")),
    ]
    markdown = to_markdown(payload, commands)
    paths = write_results(args.out, "depth-quick" if args.quick else "depth", payload, markdown)
    print(markdown)
    print("wrote " + ", ".join(map(str, paths)))
    return 0


if __name__ == "__main__":
    run_command("bench.depth", main)
