"""``popcode-train evaluate-detections``: a detections JSON + a BOP split -> COCO AP and recall per visible fraction.

The scores are the BOP toolkit's for 2-D detection (pycocotools, iouType bbox, amodal boxes, instances under
10 % visible ignored): :mod:`popcode_trainer.metrics.detection_scores` says which conventions and where it
differs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import OVERWRITE_HELP, check_output_file, json_bytes, write_json_atomic
from popcode_runtime.bop.detections import read_detections

from ..eval.reporting.markdown import markdown_table
from ..metrics.detection_scores import BOX_TYPES, COCO_SCORES, DetectionScores, detection_scores


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "evaluate-detections", help="a detections JSON + a split -> COCO AP, AR and recall per visible fraction",
        description="Score 2-D detections (the BOP challenge's default-detections JSON: {scene_id, image_id, "
                    "category_id, bbox, score, time}) against a BOP split's ground truth as the BOP toolkit's "
                    "eval_bop22_coco.py --ann_type=bbox does: COCO's AP, AP50, AP75, AR1, AR10, AR100 and their "
                    "small / medium / large parts (pycocotools), with instances under 10%% visible ignored. Also "
                    "AP per object and the recall at IoU 0.5 per visible fraction.")
    parser.add_argument("--split", type=Path, required=True, metavar="DIR", help="BOP split folder")
    parser.add_argument("--detections", type=Path, required=True, metavar="JSON",
                        help="detections of the split's images (boxes x, y, w, h px, w and h counting pixels)")
    parser.add_argument("--box", choices=BOX_TYPES, default="amodal",
                        help="ground-truth box: amodal, the whole silhouette inside the image (default, as the "
                             "toolkit), or modal, its visible part")
    parser.add_argument("--min-score", type=float, default=0.0, metavar="S",
                        help="the recall per visible fraction counts detections scored at least S (default 0: "
                             "all); AP ranks every detection")
    parser.add_argument("--json", action="store_true", help="print JSON instead of tables")
    parser.add_argument("--out", type=Path, metavar="FILE.json", help="also write the scores as JSON")
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if not 0.0 <= args.min_score <= 1.0:
        raise PopcodeError(f"--min-score must lie in [0, 1], got {args.min_score:g}")
    inputs = [args.split, args.detections]
    out = check_output_file(args.out, "--out", inputs, args.overwrite) if args.out is not None else None
    scores = detection_scores(args.split, read_detections(args.detections), args.box, args.min_score)
    if out is not None:
        write_json_atomic(out, scores.to_dict())
    if args.json:
        print(json_bytes(scores.to_dict()).decode())
    else:
        print(report(scores, args.detections, args.split))
        if out is not None:
            print(f"\nwrote {out}")
    return 0


def report(scores: DetectionScores, detections: Path, split: Path) -> str:
    """The scores as three markdown tables under a line saying what was scored."""
    head = (f"{detections} on {split}: {scores.detections} detections, {scores.images} images, "
            f"{scores.instances} instances ({scores.ignored_instances} under 10% visible, ignored); "
            f"{scores.box} boxes")
    coco = markdown_table(["score", "value"], [[name, _value(scores.coco[name])] for name in COCO_SCORES])
    objects = markdown_table(["object", "AP"], [[obj_id, _value(ap)] for obj_id, ap in scores.ap_per_object.items()])
    recalls = [*scores.recall_by_visibility, scores.recall_goal]
    visibility = markdown_table(
        ["visible", "instances", "found", "recall"],
        [[f"{r.low:g}–{r.high:g}", r.instances, r.found, _value(r.recall)] for r in recalls])
    time = "unknown" if scores.mean_time_per_image_s is None else f"{scores.mean_time_per_image_s:.3f} s"
    unannotated = [f"{count} detection{'s' * (count != 1)} of object {obj_id}"
                   for obj_id, count in scores.unannotated_detections.items()]
    if unannotated:
        head += (f"\n{', '.join(unannotated)}, which the split does not annotate, are not scored (no ground truth "
                 "defines their AP)")
    return "\n\n".join([
        head, coco, f"mean detection time per image: {time}", "AP per object", objects,
        f"recall at IoU 0.5 by visible fraction (detections scored >= {scores.min_score:g}; last row: the goal, "
        f"instances at least 30% visible)", visibility])


def _value(value: float | None) -> str:
    return "–" if value is None else f"{value:.3f}"
