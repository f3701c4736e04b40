"""Translation from the box on rendered data: the error of the runtime's box fit alone (no model needed).

    python -m bench.translation [--quick] [--out DIR]

Renders the built-in parts at random positions and places every instance with
its ground-truth rotation through the runtime's fit
(``popcode_runtime.geometry.translation``, via ``popcode_trainer.eval.pipeline.translation``): the
floor under any model's translation error. Rows compare the points the fit
uses, the hull points the export writes against the 3-D box corners (what a
model exported without meshes carries), on the rendered ``bbox_obj``; the hull
points on the exact projected box (no pixel rounding) isolate the hull
approximation (the rendered box's own error is its pixel rounding: an edge lies
anywhere within the half pixel beyond the mask's last pixel centre). The 6-D
scores of (ground-truth rotation, fitted translation) show what the fit costs in
the BOP metrics. ``popcode-train evaluate --translation`` gives the same table
for a model's own rotations.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.geometry.camera import project_points
from popcode_runtime.geometry.crop import box_from_edges
from popcode_trainer.data.bop import Instance
from popcode_trainer.data.hull import HULL_POINTS, with_hull_points
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.pipeline.split_metrics import SplitMetrics
from popcode_trainer.eval.pipeline.translation import (
    full_pose,
    object_points,
    translation_summary,
    translations_from_boxes,
)
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.eval.reporting.tables import ambiguity_markdown, translation_markdown
from tools.command import run_command
from tools.paths import RESULTS
from tools.report import machine, write_results

HULL = f"{HULL_POINTS} hull points"
CORNERS = "3-D box corners"
ROWS = (f"{HULL}, rendered box", f"{CORNERS}, rendered box", f"{HULL}, exact box")


def exact_box(instance: Instance, vertices_mm: np.ndarray) -> tuple[float, float, float, float]:
    """The unrounded BOP box ``(x, y, w, h)`` of the projected mesh in the ground-truth pose."""
    uv = project_points(vertices_mm, instance.K, instance.R_m2c, instance.t_m2c_mm)
    return box_from_edges([*uv.min(axis=0), *uv.max(axis=0)])


def per_object(t_mm: np.ndarray, instances: Sequence[Instance]) -> dict[int, dict[str, float]]:
    obj_ids = np.array([inst.obj_id for inst in instances])
    t_gt = np.stack([inst.t_m2c_mm for inst in instances])
    return {int(obj): translation_summary(t_mm[obj_ids == obj], t_gt[obj_ids == obj]) for obj in np.unique(obj_ids)}


def run_benchmark(out_dir: Path, images_per_object: int, size: int, seed: int) -> dict[str, Any]:
    """Render, fit every instance for every row, score; returns the JSON payload."""
    split_dir = render_builtin_split(out_dir / "split", images_per_object, size=(size, size), seed=seed,
                                     random_position=True, progress=True)
    models_dir = split_dir / BUILTIN_MODELS_FOLDER
    split = read_eval_split([split_dir], models_dir)
    hull = object_points(with_hull_points(split.models_info, models_dir))
    corners = object_points(split.models_info)
    instances = split.instances
    R_gt = np.stack([inst.R_m2c for inst in instances])
    t_gt = np.stack([inst.t_m2c_mm for inst in instances])
    metrics = SplitMetrics(split)
    try:
        exact = [replace(inst, box=exact_box(inst, metrics.objects[inst.obj_id].pts_mm)) for inst in instances]
        fits = dict(zip(ROWS, (translations_from_boxes(R_gt, boxes, points) for boxes, points in (
            (instances, hull), (instances, corners), (exact, hull))), strict=True))
        scores = {points_name: full_pose(R_gt, metrics, points).groups
                  for points_name, points in ((HULL, hull), (CORNERS, corners))}
    finally:
        metrics.close()
    box_px = np.array([min(inst.box[2:]) for inst in instances])
    return {
        "settings": {"images_per_object": images_per_object, "image_size_px": size, "seed": seed,
                     "instances": len(instances), "box_px_min_median_max": [float(box_px.min()),
                                                                          float(np.median(box_px)),
                                                                          float(box_px.max())]},
        "translation": {row: translation_summary(t_mm, t_gt) for row, t_mm in fits.items()},
        "per_object": {row: per_object(t_mm, instances) for row, t_mm in fits.items()},
        "full_pose_groups": scores,
    }


def to_markdown(payload: Mapping[str, Any], command: str) -> str:
    settings, description = payload["settings"], machine()
    low, median, high = settings["box_px_min_median_max"]
    objects = sorted(next(iter(payload["per_object"].values())))
    per_object_rows = [[row, *(f"{summaries[obj]['median_te_percent']:.2f}" for obj in objects)]
                       for row, summaries in payload["per_object"].items()]
    return "\n\n".join([
        "# Translation from the box, ground-truth rotation (rendered built-in parts)",
        f"Machine: {description['cpu']}, {description['cores']} cores, numpy {np.__version__}. Command: `{command}`",
        f"{settings['instances']} instances, {settings['image_size_px']} px images, boxes {low:.0f}–{high:.0f} px "
        f"(median {median:.0f}); te in mm and in % of the true distance ‖t‖.",
        translation_markdown(payload["translation"], label="Points, box"),
        "**Median te [% of ‖t‖] per object**",
        markdown_table(["Points, box", *map(str, objects)], per_object_rows),
        "**6-D scores**: ground-truth rotation, translation fitted to the rendered box",
        ambiguity_markdown(payload["full_pose_groups"]),
    ])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 images per object at 128 px (a smoke run)")
    parser.add_argument("--images", type=int, default=50, help="images per object (default 50)")
    parser.add_argument("--size", type=int, default=256, help="square image size in px (default 256)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    images, size = (3, 128) if args.quick else (args.images, args.size)
    work = args.out / f"translation-work-{images}x{size}"
    payload = run_benchmark(work, images, size, args.seed)
    command = "python -m bench.translation" + (
        " --quick" if args.quick else f" --images {images} --size {size} --seed {args.seed}")
    markdown = to_markdown(payload, command)
    paths = write_results(args.out, "translation-quick" if args.quick else "translation", payload, markdown)
    print(markdown)
    print("wrote " + ", ".join(map(str, paths)))
    return 0


if __name__ == "__main__":
    run_command("bench.translation", main)
