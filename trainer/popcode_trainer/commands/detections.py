"""``popcode-train detections``: a split's ground-truth boxes with a detector's error -> BOP default-detections JSON.

``popcode run --detections`` then runs on the boxes ``popcode-train evaluate
--box-noise`` gives the same instances (same preset and seed): one seeding rule,
in :mod:`popcode_trainer.eval.pipeline.detector_boxes`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import OVERWRITE_HELP, check_output_file, require_folder, write_json_atomic
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT, BOX_KINDS

from ..data.box_noise import BOX_NOISE_PRESETS, box_noise_preset
from ..eval.pipeline.detector_boxes import detections_json, split_detections


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "detections", help="a split's boxes with a detector's error -> BOP default-detections JSON",
        description="Write the BOP challenge's default-detections JSON (a list of {scene_id, image_id, category_id, "
                    "bbox, score, time}) from a split's ground-truth boxes, each scaled, shifted and clipped as a "
                    "detector's would be (score 1, time -1: unknown). The same preset and seed give the boxes "
                    "popcode-train evaluate --box-noise crops, so popcode run --detections on this file and "
                    "evaluate agree.")
    parser.add_argument("--split", type=Path, required=True, metavar="DIR", help="BOP split folder")
    parser.add_argument("--box-noise", required=True, metavar="PRESET",
                        help=f"the detector's error: {', '.join(BOX_NOISE_PRESETS)} (typical IoU 1, 0.9, 0.75, 0.6)")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.json", help="detections file to write")
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    parser.add_argument("--seed", type=int, default=0, metavar="N",
                        help="seed of the boxes (default 0; as evaluate's --box-noise-seed)")
    parser.add_argument("--min-visib-fract", type=float, default=BOP19_MIN_VISIB_FRACT, metavar="F",
                        help=f"leave out instances with less of the object visible (default, as BOP19 and "
                             f"evaluate: {BOP19_MIN_VISIB_FRACT})")
    parser.add_argument("--box", choices=BOX_KINDS, default="bbox_obj",
                        help="the ground-truth box of scene_gt_info.json to start from (default bbox_obj, as "
                             "evaluate)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    noise = box_noise_preset(args.box_noise)
    if args.seed < 0:
        raise PopcodeError(f"--seed must be 0 or more, got {args.seed}")
    if not 0.0 <= args.min_visib_fract <= 1.0:
        raise PopcodeError(f"--min-visib-fract must lie in [0, 1], got {args.min_visib_fract}")
    out = check_output_file(args.out, "--out", [args.split], args.overwrite)
    require_folder(args.split, "split folder")
    detections, iou = split_detections(args.split, noise, args.seed, args.box, args.min_visib_fract)
    write_json_atomic(out, detections_json(detections))
    images = len({d.image_key for d in detections})
    print(f"wrote {out}: {len(detections)} detections in {images} images, box-noise preset {args.box_noise!r} "
          f"seed {args.seed}, IoU with the true box mean {iou.mean():.3f}, min {iou.min():.3f}")
    return 0
