"""Translation from depth on a rendered cluttered split: box vs depth vs depth + ICP, true and model rotations.

    python -m bench.depth [--quick] [--scenes 12] [--size 720 540] [--sensor industrial] [--seed 2000]
        [--models models/builtin-parts-1-2.onnx models/builtin-parts-3-6.onnx] [--out bench/results]

Renders a cluttered bin split of the built-in parts (the demo's cluttered test seed, the sensor preset's
depth noise included) and places every instance at least 10 % visible (BOP19's targets) in its
ground-truth box three ways: the runtime's fit to the box (:mod:`popcode_runtime.translation`), the
translation from depth (:mod:`popcode_runtime.depth`), and depth followed by GICP refinement of rotation
and translation (:mod:`popcode_runtime.depth_refine`); each from the ground-truth rotation (the floor of
each method) and from the models' rotations through :class:`~popcode_runtime.PoseEstimator` (what a robot
gets; the models' metadata is given the meshes' surface points, as a fresh export writes them). Reported:
translation error (median mm and % of the distance, shares under 2 mm, 5 mm and 2 % of the distance), the
rotation error up to symmetry (refinement changes it), where the translations came from, and milliseconds
per instance of each step on one thread (from the ground-truth rows, which time the steps alone).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime import PoseEstimator, read_image
from popcode_runtime.depth import TranslationSource, check_depth, object_surface, read_depth
from popcode_runtime.depth_pose import pose_with_depth
from popcode_runtime.engine import OnnxEngine
from popcode_runtime.symmetries import (
    SymmetryClass,
    continuous_axis,
    rotation_error_up_to_symmetry,
    symmetry_class,
    symmetry_rotations,
)
from popcode_runtime.translation import object_points_mm, translation_from_box
from popcode_trainer.data.bop import Instance, read_bop_split
from popcode_trainer.data.hull import with_hull_points
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.eval.pipeline.translation import translation_summary
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.pose_errors import translation_error_mm

from .report import machine, machine_line, write_results

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = (ROOT / "models" / "builtin-parts-1-2.onnx", ROOT / "models" / "builtin-parts-3-6.onnx")
BOX, DEPTH, REFINED = "box", "depth", "depth + ICP"
MIN_VISIB_FRACT = 0.1  # BOP19's targets
CLUTTERED_TEST_SEED = 2000  # the demo's cluttered test split (seed + 2000 with the default seed 0)


@dataclasses.dataclass
class Placements:
    """One row's poses, instance by instance, and the seconds each took."""

    t_mm: list[np.ndarray] = dataclasses.field(default_factory=list)
    R: list[np.ndarray] = dataclasses.field(default_factory=list)
    sources: list[str] = dataclasses.field(default_factory=list)
    seconds: list[float] = dataclasses.field(default_factory=list)

    def add(self, R: np.ndarray, t_mm: np.ndarray, source: str, seconds: float) -> None:
        self.R.append(R)
        self.t_mm.append(t_mm)
        self.sources.append(source)
        self.seconds.append(seconds)


class DepthImages:
    """Each image's depth in mm, read once."""

    def __init__(self) -> None:
        self._cache: dict[Path, np.ndarray] = {}

    def __call__(self, instance: Instance) -> np.ndarray:
        if instance.depth_path not in self._cache:
            raw = read_depth(instance.depth_path)
            self._cache[instance.depth_path] = check_depth(raw, raw.shape, instance.depth_scale)
        return self._cache[instance.depth_path]


def timed(call: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``call(*args)`` and the seconds it took."""
    started = time.perf_counter()
    result = call(*args)
    return result, time.perf_counter() - started


def true_rotation_rows(instances: Sequence[Instance], objects: Mapping[int, dict[str, Any]],
                       depths: DepthImages) -> dict[str, Placements]:
    """Each method from the ground-truth rotation, each step timed alone."""
    rows = {BOX: Placements(), DEPTH: Placements(), REFINED: Placements()}
    for inst in instances:
        info, depth_mm = objects[inst.obj_id], depths(inst)
        surface, hull = object_surface(info), object_points_mm(info)
        t_box, seconds = timed(translation_from_box, inst.R_m2c, inst.box, inst.K, hull)
        rows[BOX].add(inst.R_m2c, t_box, TranslationSource.BOX, seconds)
        for method, refine in ((DEPTH, False), (REFINED, True)):
            pose, seconds = timed(pose_with_depth, [inst.R_m2c], inst.box, inst.K, depth_mm, surface, hull, info,
                                  refine)
            rows[method].add(pose.R_m2c, pose.t_m2c_mm, source_text(pose.source, pose.note), seconds)
    return rows


def source_text(source: str, note: str | None) -> str:
    """A translation's source and the kind of its note (the note without its numbers), for counting."""
    return f"{source}" if note is None else f"{source} ({note.split(':')[0].split(';')[0].split(' (')[0]})"


def model_rotation_rows(instances: Sequence[Instance], estimators: Mapping[int, PoseEstimator],
                        depths: DepthImages) -> dict[str, Placements]:
    """Each method from the models' rotations, through ``PoseEstimator.predict`` image by image."""
    rows = {BOX: Placements(), DEPTH: Placements(), REFINED: Placements()}
    by_image: dict[Path, list[int]] = defaultdict(list)
    for index, inst in enumerate(instances):
        by_image[inst.image_path].append(index)
    found: dict[str, dict[int, tuple[np.ndarray, np.ndarray, str, float]]] = {method: {} for method in rows}
    for image_path, indices in by_image.items():
        image, depth_mm = read_image(image_path), depths(instances[indices[0]])
        for estimator in {id(e): e for e in estimators.values()}.values():
            mine = [i for i in indices if estimators[instances[i].obj_id] is estimator]
            if not mine:
                continue
            boxes, ids = [instances[i].box for i in mine], [instances[i].obj_id for i in mine]
            K = instances[mine[0]].K
            for method, options in ((BOX, {"translation": True}), (DEPTH, {"depth": depth_mm}),
                                    (REFINED, {"depth": depth_mm, "refine_depth": True})):
                predictions = estimator.predict(image, boxes, K=K, obj_ids=ids, **options)
                per_instance = estimator.last_timings.depth_s / len(mine)
                for i, p in zip(mine, predictions, strict=True):
                    found[method][i] = (p.R_m2c, p.t_m2c_mm, source_text(p.t_source, p.depth_note), per_instance)
    for method, placements in rows.items():
        for i in range(len(instances)):
            placements.add(*found[method][i])
    return rows


def summary(placements: Placements, instances: Sequence[Instance], objects: Mapping[int, dict[str, Any]],
            timed_steps: bool) -> dict[str, Any]:
    """Translation and rotation errors of one row, its sources and its milliseconds per instance."""
    t_gt = np.stack([inst.t_m2c_mm for inst in instances])
    t_mm = np.stack(placements.t_mm)
    te_mm = translation_error_mm(t_mm, t_gt)
    rotation_deg = np.array([rotation_error_deg(R, inst, objects[inst.obj_id])
                             for R, inst in zip(placements.R, instances, strict=True)])
    return {
        **translation_summary(t_mm, t_gt),
        "within_2_mm": float(np.mean(te_mm < 2.0)),
        "within_5_mm": float(np.mean(te_mm < 5.0)),
        "median_rotation_error_deg": float(np.median(rotation_deg)),
        "rotation_within_5_deg": float(np.mean(rotation_deg < 5.0)),
        "sources": dict(Counter(placements.sources).most_common()),
        "median_ms": float(1000.0 * np.median(placements.seconds)) if timed_steps else None,
        "p90_ms": float(1000.0 * np.percentile(placements.seconds, 90)) if timed_steps else None,
    }


def rotation_error_deg(R: np.ndarray, inst: Instance, info: Mapping[str, Any]) -> float:
    """The rotation error up to the object's symmetries [deg] (the axis alone for a continuous symmetry)."""
    axis = continuous_axis(info) if symmetry_class(info) == SymmetryClass.CONTINUOUS else None
    error = rotation_error_up_to_symmetry(R[None], inst.R_m2c[None], symmetry_rotations(info), axis)
    return float(np.degrees(error[0]))


def model_estimators(paths: Sequence[Path], models_dir: Path) -> dict[int, PoseEstimator]:
    """Object id -> an estimator (one thread) of the model that knows it, its objects given the surface points of
    the meshes in ``models_dir`` as an export from this version writes them."""
    estimators: dict[int, PoseEstimator] = {}
    for path in paths:
        engine = OnnxEngine(path, threads=1)
        objects = with_hull_points(engine.metadata.objects, models_dir)
        estimator = PoseEstimator.from_engine(engine, dataclasses.replace(engine.metadata, objects=objects))
        estimators.update({obj_id: estimator for obj_id in objects})
    return estimators


def run_benchmark(split_dir: Path, models: Sequence[Path]) -> dict[str, Any]:
    """Place every instance of the split with every method; returns the JSON payload."""
    split = read_bop_split(split_dir, split_dir / BUILTIN_MODELS_FOLDER, min_visib_fract=MIN_VISIB_FRACT)
    objects = with_hull_points(split.models_info, split.models_dir)
    instances, depths = split.instances, DepthImages()
    results: dict[str, dict[str, Any]] = {}
    estimators = model_estimators(models, split.models_dir)
    for name, rows in (("ground-truth rotation", true_rotation_rows(instances, objects, depths)),
                       ("model rotation", model_rotation_rows(instances, estimators, depths))):
        for method, placements in rows.items():
            results[f"{name}, {method}"] = summary(placements, instances, objects, name.startswith("ground"))
    distance_mm = np.linalg.norm(np.stack([inst.t_m2c_mm for inst in instances]), axis=1)
    return {"settings": {"instances": len(instances), "images": len({inst.image_path for inst in instances}),
                         "distance_mm_min_median_max": [float(distance_mm.min()), float(np.median(distance_mm)),
                                                        float(distance_mm.max())],
                         "models": [str(path) for path in models]},
            "rows": results}


def to_markdown(payload: Mapping[str, Any], command: str, split: Mapping[str, Any]) -> str:
    settings = payload["settings"]
    low, median, high = settings["distance_mm_min_median_max"]
    header = ["Rotation, translation", "median te [mm]", "median te [% of ‖t‖]", "te < 2 mm", "te < 5 mm",
              "te < 2 %", "median re [°]", "re < 5°", "ms / instance (median, p90)", "sources"]
    rows = []
    for name, row in payload["rows"].items():
        ms = "" if row["median_ms"] is None else f"{row['median_ms']:.2f}, {row['p90_ms']:.2f}"
        sources = "; ".join(f"{source} {count}" for source, count in row["sources"].items())
        rows.append([name, f"{row['median_te_mm']:.2f}", f"{row['median_te_percent']:.2f}",
                     f"{100 * row['within_2_mm']:.0f} %", f"{100 * row['within_5_mm']:.0f} %",
                     f"{100 * row['within_2_percent']:.0f} %", f"{row['median_rotation_error_deg']:.2f}",
                     f"{100 * row['rotation_within_5_deg']:.0f} %", ms, sources])
    return "\n\n".join([
        "# Translation from depth: box vs depth vs depth + ICP (rendered cluttered split)",
        machine_line(machine()) + f" Command: `{command}`",
        f"{split['scenes']} scenes at {split['size'][0]}×{split['size'][1]} px, sensor `{split['sensor']}`, seed "
        f"{split['seed']}; {settings['instances']} instances at least {100 * MIN_VISIB_FRACT:.0f} % visible in "
        f"{settings['images']} images, distance {low:.0f}–{high:.0f} mm (median {median:.0f}); ground-truth boxes "
        f"(`bbox_obj`). Models: {', '.join(Path(m).name for m in settings['models'])}. te: translation error, "
        "re: rotation error up to symmetry (axis alone for a continuous symmetry). Milliseconds on one thread: "
        "box = the box fit; depth = box fit + depth; depth + ICP = box fit + depth + GICP.",
        markdown_table(header, rows),
    ])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 scenes at 360x270 (a smoke run)")
    parser.add_argument("--scenes", type=int, default=12, help="scene images to render (default 12)")
    parser.add_argument("--size", type=int, nargs=2, default=(720, 540), metavar=("W", "H"))
    parser.add_argument("--sensor", default="industrial", help="sensor preset of the scenes (default industrial)")
    parser.add_argument("--seed", type=int, default=CLUTTERED_TEST_SEED)
    parser.add_argument("--models", type=Path, nargs="+", default=list(SHIPPED))
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    scenes, size = (3, (360, 270)) if args.quick else (args.scenes, tuple(args.size))
    split = {"scenes": scenes, "size": list(size), "sensor": args.sensor, "seed": args.seed}
    work = args.out / f"depth-work-{scenes}x{size[0]}-{args.sensor}-{args.seed}"
    render_cluttered_test_split(work, scenes=scenes, size=size, seed=args.seed, sensor=args.sensor, progress=True)
    payload = {"split": split, **run_benchmark(work, args.models)}
    command = "python -m bench.depth" + (" --quick" if args.quick else
                                         f" --scenes {scenes} --size {size[0]} {size[1]} --sensor {args.sensor} "
                                         f"--seed {args.seed}")
    markdown = to_markdown(payload, command, split)
    paths = write_results(args.out, "depth-quick" if args.quick else "depth", payload, markdown)
    print(markdown)
    print("wrote " + ", ".join(map(str, paths)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
