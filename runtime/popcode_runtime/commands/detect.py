"""The ``popcode detect`` command line: a popcode detector on one image (boxes printed) or on every image of a
BOP split (the BOP challenge's default-detections JSON, which ``popcode run --detections`` and the BOP toolkit
read)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable, Mapping
from pathlib import Path

from ..base.files import OVERWRITE_HELP, check_output_file, require_folder, write_json_atomic
from ..bop.detections import Detection
from ..bop.split import SplitImage, split_images
from ..geometry.crop import MAX_IMAGE_PIXELS, read_image_file
from ..inference.detector import Detector
from ..model.detector_metadata import MAX_DETECTIONS
from .run_loop import Progress
from .run_results import ImageKey, out_lock


def add_detector_options(parser: argparse.ArgumentParser) -> None:
    """The thresholds a detector runs with (default: the ones its file carries)."""
    parser.add_argument("--score-threshold", type=float, metavar="S",
                        help="keep boxes scoring at least S, in (0, 1] (default: the detector's own)")
    parser.add_argument("--nms-iou", type=float, metavar="IOU",
                        help="suppress a box overlapping a better one of its object by more than IOU, in (0, 1] "
                             "(default: the detector's own)")
    parser.add_argument("--max-detections", type=int, metavar="N",
                        help=f"at most N boxes a frame, 1 to {MAX_DETECTIONS} (default: the detector's own)")


def open_detector(args: argparse.Namespace) -> Detector:
    """The ``--detector`` (or ``detector``) file with the command line's thresholds."""
    return Detector(args.detector, providers=args.provider, threads=args.threads,
                    score_threshold=args.score_threshold, nms_iou=args.nms_iou, max_detections=args.max_detections)


def skipped_line(skipped: Mapping[int, int]) -> str:
    """The line that counts a frame's (or a run's) detections no given model knows, by object."""
    total = sum(skipped.values())
    return (f"skipped {total} detection{'' if total == 1 else 's'} of objects no model knows: "
            + ", ".join(f"object {obj_id} x{count}" for obj_id, count in sorted(skipped.items())))


def register(commands: argparse._SubParsersAction, add_runtime_options: Callable[[argparse.ArgumentParser], None]
             ) -> None:
    detect = commands.add_parser(
        "detect", help="every part's box in an image, or in every image of a BOP split -> detections JSON",
        description="Run a popcode detector (popcode-train train-detector) on IMAGE and print each box, or on every "
                    "image of --split and write the BOP challenge's default-detections JSON (a list of {scene_id, "
                    "image_id, category_id, bbox, score, time}; time: the detector's seconds for the image).")
    detect.add_argument("detector", type=Path, help="popcode detector ONNX file")
    detect.add_argument("image", nargs="?", type=Path, help="image file (grey or colour, 8 or 16 bit)")
    detect.add_argument("--split", type=Path, metavar="DIR", help="BOP split folder instead of IMAGE")
    detect.add_argument("--out", type=Path, metavar="JSON", help="with --split: the detections file to write")
    detect.add_argument("--overwrite", action="store_true", help=f"--out: {OVERWRITE_HELP}")
    detect.add_argument("--max-images", type=int, metavar="N", help="with --split: only its first N images")
    detect.add_argument("--json", action="store_true", help="IMAGE: print JSON instead of text")
    detect.add_argument("--quiet", action="store_true",
                        help="no progress, summary or timing line (one IMAGE's boxes are still printed, errors too)")
    detect.add_argument("--max-pixels", type=int, default=MAX_IMAGE_PIXELS, metavar="N",
                        help=f"refuse images of more pixels, before decoding them (default {MAX_IMAGE_PIXELS})")
    add_detector_options(detect)
    add_runtime_options(detect)
    detect.set_defaults(handler=handle)


def detect_split(detector: Detector, images: Mapping[ImageKey, SplitImage], max_images: int | None = None,
                 progress: bool = True) -> list[Detection]:
    """Every box the detector finds in the split's images (the first ``max_images`` by scene and image id), each
    with the detector's seconds for its image (reading the file not counted, as BOP times a detector)."""
    keys = sorted(images)[:max_images]
    bar, detections = Progress(len(keys), progress, "popcode detect"), []
    for key in keys:
        found = detector.detect(read_image_file(images[key].path))
        detections += [Detection(key[0], key[1], d.obj_id, d.box, d.score, detector.last_seconds) for d in found]
        bar.step()
    return detections


def detections_json(detections: list[Detection]) -> list[dict[str, object]]:
    """BOP's default-detections entries."""
    return [{"scene_id": d.scene_id, "image_id": d.im_id, "category_id": d.obj_id,
             "bbox": [round(v, 2) for v in d.box], "score": round(d.score, 5), "time": round(d.time_s, 5)}
            for d in detections]


def handle(args: argparse.Namespace) -> int:
    if args.split is not None:
        require_folder(args.split, "--split")
        with out_lock(args.out):  # checked and written by one writer: a second detect or run is refused
            check_output_file(args.out, "--out", [args.split, args.detector], args.overwrite)
            detector = open_detector(args)
            detections = detect_split(detector, split_images(args.split), args.max_images, not args.quiet)
            write_json_atomic(args.out, detections_json(detections))
        if not args.quiet:
            images = len({d.image_key for d in detections})
            print(f"wrote {args.out}: {len(detections)} detections in {images} images")
        return 0
    detector = open_detector(args)
    found = detector.detect(read_image_file(args.image, args.max_pixels))
    if args.json:
        print(json.dumps({"detector": str(args.detector), "image": str(args.image), "seconds": detector.last_seconds,
                          "detections": [d.to_dict() for d in found]}, indent=2))
        return 0
    for d in found:
        print(f"object {d.obj_id}: box [{', '.join(f'{v:.1f}' for v in d.box)}], score {d.score:.3f}")
    if not args.quiet:
        print(f"{len(found)} detections in {1000 * detector.last_seconds:.1f} ms", file=sys.stderr)
    return 0
