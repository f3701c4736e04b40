"""The ``popcode run`` command line: a BOP split and a detector's boxes (or its own) -> a BOP19 results file."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from ..base.errors import PopcodeError
from ..base.files import OVERWRITE_HELP, check_writable_file, refuse_inputs, require_folder
from ..bop.detections import ground_truth_boxes, read_detections
from ..bop.split import BOP19_MIN_VISIB_FRACT, BOX_KINDS, split_images
from ..inference.estimator import PoseEstimator
from ..model.decoding import DECODERS
from .detect import add_detector_options, detect_split, open_detector, skipped_line
from .run_fingerprint import run_fingerprint
from .run_loop import check_pictures, run_detections
from .run_results import PartialResults, companion_paths, sources_path

DEFAULT_OUT = "results.csv"


def register(commands: argparse._SubParsersAction, add_runtime_options: Callable[[argparse.ArgumentParser], None],
             ) -> None:
    run = commands.add_parser(
        "run", help="poses for every detection of a BOP split -> BOP19 results CSV",
        description="Read a BOP split's images and a detector's boxes (the BOP challenge's default-detections "
                    "JSON) or the split's own boxes, estimate the rotation of each box in one batch per image, fit "
                    "the translation to the box with the image's cam_K (or read it from the depth with --depth), and "
                    "write a BOP19 results CSV "
                    "(scene_id,im_id,obj_id,score,R,t,time). Detections of objects no model knows are skipped and "
                    "counted. An interrupted run resumes where it stopped when given the same command.")
    run.add_argument("models", nargs="+", type=Path, metavar="MODEL",
                     help="popcode ONNX model(s); each detection goes to the model that knows its object")
    run.add_argument("--split", type=Path, required=True, metavar="DIR",
                     help="BOP split folder (scene folders with rgb/ or gray/ images and scene_camera.json)")
    source = run.add_mutually_exclusive_group(required=True)
    source.add_argument("--detections", type=Path, metavar="JSON",
                        help="detections in the BOP challenge's format: a list of {scene_id, image_id, category_id, "
                             "bbox, score, time}")
    source.add_argument("--gt-boxes", action="store_true",
                        help="use the split's own boxes (scene_gt_info.json): the paper's protocol")
    source.add_argument("--detector", type=Path, metavar="DET.onnx",
                        help="find the parts in each image with this popcode detector (popcode-train "
                             "train-detector): from the camera frame alone")
    add_detector_options(run)
    run.add_argument("--box-kind", choices=BOX_KINDS, default="bbox_obj",
                     help="with --gt-boxes: which box of scene_gt_info.json (default bbox_obj)")
    run.add_argument("--min-visib-fract", type=float, default=BOP19_MIN_VISIB_FRACT, metavar="F",
                     help=f"with --gt-boxes: leave out instances less visible (default, as BOP19: "
                          f"{BOP19_MIN_VISIB_FRACT})")
    run.add_argument("--out", default=DEFAULT_OUT, metavar="CSV",  # text: a Path would drop the / of "results/"
                     help=f"results file to write (default {DEFAULT_OUT}; <CSV>.partial while running)")
    run.add_argument("--max-images", type=int, metavar="N", help="only the first N images with detections")
    run.add_argument("--decoder", choices=DECODERS, default="argmax",
                     help="argmax: the paper's winning neuron (default); refined: sub-neuron estimate")
    run.add_argument("--draw", type=Path, metavar="DIR",
                     help="also write a picture of each image's estimates into DIR (<scene_id>_<im_id>.png)")
    run.add_argument("--depth", action="store_true",
                     help="the translation from each image's depth image (depth/ and scene_camera.json's "
                          "depth_scale) instead of the box; where an instance's depth is unusable it keeps the box's. "
                          "Each estimate's source is written to <CSV stem>.translation<CSV suffix> "
                          "(results.translation.csv)")
    run.add_argument("--refine", action="store_true",
                     help="with --depth: also refine rotation and translation against the observed points (ICP; "
                          "needs pip install ./runtime[depth])")
    run.add_argument("--overwrite", action="store_true",
                     help=f"{OVERWRITE_HELP}: a finished --out, pictures in --draw")
    run.add_argument("--quiet", action="store_true", help="no progress line")
    add_runtime_options(run)
    run.set_defaults(handler=handle)


def handle(args: argparse.Namespace) -> int:
    inputs = [args.split, *args.models, *filter(None, [args.detections, args.detector])]
    args.out = check_writable_file(args.out, "--out", inputs)
    for companion in companion_paths(args.out):
        check_writable_file(companion, "--out", inputs)
    if args.draw is not None:
        require_folder(args.draw, "--draw folder")
        refuse_inputs(args.draw, "--draw folder", inputs)
    require_folder(args.split, "split folder")
    estimators = [PoseEstimator(path, providers=args.provider, threads=args.threads, decoder=args.decoder)
                  for path in args.models]
    images = split_images(args.split)
    results = None
    if args.detector:
        detector = open_detector(args)
        known = {obj_id for estimator in estimators for obj_id in estimator.metadata.objects}
        if not known & set(detector.obj_ids):
            raise PopcodeError(f"{args.detector} finds objects {list(detector.obj_ids)} and the models know objects "
                               f"{sorted(known)}: none in common (wrong detector or wrong models?)")
        # what the outputs refuse is said before the detector's progress lines: --out (its lock, a finished file,
        # another run's partial) and the pictures of the images it looks at
        fingerprint = run_fingerprint(args, images)
        results = PartialResults(args.out, fingerprint, args.overwrite)
        try:
            if args.draw is not None:
                check_pictures(args.draw, sorted(images)[:args.max_images], args.out, inputs, args.overwrite)
            detections = detect_split(detector, images, args.max_images, not args.quiet)
        except BaseException:
            results.close()
            raise
    else:
        detections = read_detections(args.detections) if args.detections else \
            ground_truth_boxes(args.split, args.box_kind, args.min_visib_fract)
        fingerprint = run_fingerprint(args, images)  # after the detections are read: a missing file is named so
    summary = run_detections(estimators, [str(path) for path in args.models], images, detections, out=args.out,
                             fingerprint=fingerprint, max_images=args.max_images, progress=not args.quiet,
                             draw_dir=args.draw, depth=args.depth, refine=args.refine, overwrite=args.overwrite,
                             inputs=inputs, results=results)
    resumed = f" ({summary.images_resumed} done by an earlier run)" if summary.images_resumed else ""
    print(f"wrote {args.out}: {summary.estimates} estimates of {summary.images_done} images{resumed} in "
          f"{summary.seconds:.1f} s")
    if args.depth:
        print(f"translation sources ({sources_path(args.out)}): "
              + ", ".join(f"{source} {count}" for source, count in summary.sources.items()))
    if summary.skipped:
        print(skipped_line(summary.skipped))
    return 0
