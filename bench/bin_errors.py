"""Where a model's rotation errors in the bin come from: a neighbour's pose, a flip, or plain error.

    python -m bench.bin_errors --model models/builtin-parts-3-6.onnx --split VAL_CLEAN --split VAL_BIN
        [--min-visib-fract 0.1] [--out bench/results] [--name bin-errors]

MSSD says how much a bin costs, not why. For every instance (ground-truth boxes, ``bbox_obj``) of each split this
counts, per visible-fraction bin (:data:`VISIBILITY_BINS`): the median rotation error up to the part's
symmetries; the share of gross errors (over :data:`GROSS_DEG`); of those, how many are near-flips (over
:data:`FLIP_DEG`: a look-alike pose of a part without a declared symmetry), and how many equal the pose of another
instance of the same part whose box overlaps this one's (within :data:`NEIGHBOUR_DEG`: the network read the
neighbour instead of the target, which a crop of a bin invites); and the boxes' sizes, since a bin's parts may
be seen larger or smaller than the clean images'. The answer points at the lever: neighbour reads ask for a
target cue, flips for look-alike training, plain errors for more capacity or data.
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
from popcode_trainer.data.box_noise import box_intersection
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.confidence import rotation_errors_deg
from popcode_trainer.metrics.recall import VISIBILITY_BINS

from .command import run_command
from .report import machine, machine_line, write_results

GROSS_DEG = 30.0  # an error past this is a wrong pose, not an imprecise one
FLIP_DEG = 150.0  # a wrong pose this far off is the part turned round: a look-alike
NEIGHBOUR_DEG = 20.0  # a wrong pose this close to an overlapping same-part instance's is that instance's
NEIGHBOUR_OVERLAP = 0.05  # share of the target's box another instance's box must cover to count as a neighbour


def _box_overlap(target: Sequence[float], other: Sequence[float]) -> float:
    """The share of ``target``'s box (x, y, w, h) that ``other`` covers."""
    return box_intersection(target, other) / (target[2] * target[3])


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
                          and _box_overlap(target.box, o.box) > NEIGHBOUR_OVERLAP]
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


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts of one group of instances (see the module's docstring)."""
    errors = np.array([r["error_deg"] for r in rows])
    gross = [r for r in rows if r["error_deg"] > GROSS_DEG]
    return {"instances": len(rows), "median_error_deg": float(np.median(errors)) if rows else None,
            "gross": len(gross), "flips": sum(r["error_deg"] > FLIP_DEG for r in gross),
            "gross_with_neighbour": sum(r["neighbour_deg"] is not None for r in gross),
            "neighbour_reads": sum(r["neighbour_deg"] is not None and r["neighbour_deg"] < NEIGHBOUR_DEG
                                   for r in gross),
            "median_box_px": float(np.median([r["box_px"] for r in rows])) if rows else None}


def groups(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """:func:`summary` of all instances, of each visible-fraction bin and of each part."""
    result = {"all": summary(rows)}
    for label, low, high in VISIBILITY_BINS:
        chosen = [r for r in rows if low <= r["visib_fract"] < high]
        if chosen:
            result[f"visible {label}"] = summary(chosen)
    for obj_id in sorted({r["obj_id"] for r in rows}):
        result[f"part {obj_id}"] = summary([r for r in rows if r["obj_id"] == obj_id])
    return result


def _share(count: int, total: int) -> str:
    return f"{count} ({100 * count / total:.0f} %)" if total else "0"


def to_markdown(payload: dict[str, Any]) -> str:
    lines = [f"# Where the rotation errors come from: {payload['name']}", "",
             f"`python -m bench.bin_errors {payload['arguments']}`. Ground-truth boxes (`bbox_obj`), instances "
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
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
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
    run_command("bin_errors", main)
