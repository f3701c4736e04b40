"""Where a model's rotation errors in the bin come from: a neighbour's pose, a flip, or plain error.

    python -m experiments.bin_errors --model models/builtin-parts-3-6.onnx --split VAL_CLEAN --split VAL_BIN
        [--min-visib-fract 0.1] [--out bench/results] [--name bin-errors]

MSSD says how much a bin costs, not why. For every instance (ground-truth boxes, ``bbox_obj``) of each split this
reads the model's rotation error and that of the pose of each other instance of the same part whose box overlaps
this one's (a crop of a bin invites reading the neighbour instead of the target), and counts them per
visible-fraction bin and per part (:mod:`tools.error_sources`: gross errors, flips, neighbour reads, the boxes'
sizes, since a bin's parts may be seen larger or smaller than the clean images'). The answer points at the lever:
neighbour reads ask for a target cue, flips for look-alike training, plain errors for more capacity or data.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.split import scene_folders, scene_ground_truth, split_images
from popcode_runtime.geometry.crop import read_image
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_trainer.data.bop import gt_rotation
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.confidence import rotation_errors_deg
from tools.command import run_command
from tools.error_sources import FLIP_DEG, GROSS_DEG, NEIGHBOUR_DEG, NEIGHBOUR_OVERLAP, box_overlap, groups
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results


def instance_rows(estimator: PoseEstimator, split: Path, min_visib_fract: float) -> list[dict[str, Any]]:
    """One row per instance of the model's parts: obj_id, visible fraction, box size, error [deg], nearest
    overlapping same-part instance's pose's error [deg] (None without one)."""
    images = split_images(split)
    models_info = estimator.metadata.objects
    obj_ids = set(models_info)
    rows = []
    for scene_dir in scene_folders(split):
        everyone = dict(scene_ground_truth(scene_dir, "bbox_obj", 0.0, obj_ids))
        for im_id, targets in scene_ground_truth(scene_dir, "bbox_obj", min_visib_fract, obj_ids):
            if not targets:
                continue
            image = read_image(images[(int(scene_dir.name), im_id)].path)
            predictions = estimator.predict(image, [t.box for t in targets], obj_ids=[t.obj_id for t in targets])
            for target, prediction in zip(targets, predictions, strict=True):
                others = [o for o in everyone[im_id] if o.gt_index != target.gt_index and o.obj_id == target.obj_id
                          and box_overlap(target.box, o.box) > NEIGHBOUR_OVERLAP]
                poses = np.stack([gt_rotation(target)] + [gt_rotation(o) for o in others])
                errors = rotation_errors_deg(np.repeat(prediction.R_m2c[None], len(poses), axis=0), poses,
                                             np.full(len(poses), target.obj_id), models_info)
                rows.append({"obj_id": target.obj_id, "visib_fract": target.visib_fract,
                             "box_px": max(target.box[2], target.box[3]), "error_deg": float(errors[0]),
                             "neighbour_deg": float(errors[1:].min()) if others else None})
    if not rows:
        raise PopcodeError(f"{split}: no instance of the model's parts {sorted(obj_ids)} is at least "
                           f"{min_visib_fract} visible")
    return rows


def _share(count: int, total: int) -> str:
    return f"{count} ({100 * count / total:.0f} %)" if total else "0"


def to_markdown(payload: dict[str, Any]) -> str:
    lines = [f"# Where the rotation errors come from: {payload['name']}", "",
             f"`python -m experiments.bin_errors {payload['arguments']}`. Ground-truth boxes (`bbox_obj`), instances "
             f">= {payload['min_visib_fract']} visible, errors up to each part's symmetries; gross: over "
             f"{GROSS_DEG:.0f}°, flip: over {FLIP_DEG:.0f}°, neighbour read: within {NEIGHBOUR_DEG:.0f}° of an "
             f"overlapping instance of the same part.", "", machine_line(payload["machine"]), ""]
    header = ["instances", "count", "median box px", "median error °", "gross", "of them flips",
              "with a same-part neighbour", "neighbour reads"]
    for split, result in payload["splits"].items():
        lines += [f"## {split}", ""]
        table = [[group, s["instances"], f"{s['median_box_px']:.0f}", f"{s['median_error_deg']:.1f}",
                  _share(s["gross"], s["instances"]), _share(s["flips"], s["gross"]),
                  _share(s["gross_with_neighbour"], s["gross"]), _share(s["neighbour_reads"], s["gross"])]
                 for group, s in result.items()]
        lines += [markdown_table(header, table), ""]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, required=True, help="ONNX model of popcode")
    parser.add_argument("--split", type=Path, action="append", required=True, help="BOP split (repeatable)")
    parser.add_argument("--min-visib-fract", type=float, default=0.1)
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime threads")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--name", default="bin-errors")
    args = parser.parse_args(argv)
    if not 0.0 <= args.min_visib_fract <= 1.0:
        parser.error("--min-visib-fract must be within [0, 1]")
    estimator = PoseEstimator(args.model, threads=args.threads)
    splits = {split.name: groups(instance_rows(estimator, split, args.min_visib_fract)) for split in args.split}
    arguments = " ".join(sys.argv[1:] if argv is None else argv)
    payload = {"name": args.name, "arguments": arguments, "model": str(args.model),
               "min_visib_fract": args.min_visib_fract, "splits": splits, "machine": machine()}
    write_results(args.out, args.name, payload, to_markdown(payload))
    print(to_markdown(payload), flush=True)
    return payload


if __name__ == "__main__":
    run_command("experiments.bin_errors", main)
