"""Which options of a ``popcode`` command need which, and the bounds of its counts: checked in one place.

Each command's parsed options are checked here before anything is read or
run, so that a typo costs one line, not a loaded model. The Python API checks
its own arguments (``PoseEstimator.predict``); this is the command line's word
for the same rules, naming the options a user typed.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

from ..base.errors import PopcodeError
from ..inference.benchmark import MAX_BENCH_BATCH
from ..inference.request import MAX_BOXES_PER_CALL


@dataclass(frozen=True)
class Needs:
    """``option`` (an argparse destination) is given only with ``needed``; ``why`` is the refusal's line."""

    option: str
    needed: str
    why: str


NEEDS: dict[str, tuple[Needs, ...]] = {
    "predict": (
        Needs("code", "json", "--code prints the raw network output in the JSON; add --json"),
        Needs("refine", "depth", "--refine is about the depth image: add --depth PNG"),
        Needs("depth_scale", "depth", "--depth-scale is about the depth image: add --depth PNG"),
        Needs("crop_origin", "K", "--crop-origin places IMAGE in the frame of the camera --K: add --K"),
    ),
    "run": (
        Needs("refine", "depth", "--refine refines the pose against each image's depth: add --depth"),
        *(Needs(option, "detector", f"--{option.replace('_', '-')} sets how --detector runs: add --detector DET.onnx")
          for option in ("score_threshold", "nms_iou", "max_detections")),
    ),
    "detect": (
        Needs("out", "split", "--out writes the detections of a --split; for one IMAGE the boxes are printed"),
        Needs("max_images", "split", "--max-images counts the images of a --split"),
    ),
}
DEFAULT_BENCH_BATCHES = (1, 8, 32)


def given(args: argparse.Namespace, option: str) -> bool:
    """Whether the command line set ``option`` (a flag that is on, or a value that is not left out)."""
    return getattr(args, option, None) not in (None, False)


def check_options(args: argparse.Namespace) -> None:
    """Refuse, in one line, options without the option they need and counts out of bounds."""
    for rule in NEEDS.get(args.command, ()):
        if given(args, rule.option) and not given(args, rule.needed):
            raise PopcodeError(rule.why)
    CHECKS.get(args.command, lambda _args: None)(args)


def _check_predict(args: argparse.Namespace) -> None:
    if (args.box is None) == (args.detector is None):
        raise PopcodeError("give the objects' boxes (--box X,Y,W,H, repeatable) or a detector to find them "
                           "(--detector DET.onnx), one of the two")
    if args.detector is None and len(args.models) > 1:
        raise PopcodeError(f"{len(args.models)} models with --box: boxes given by hand go to one MODEL; several "
                           "models are for --detector, whose boxes each go to the model of their object")
    if args.detector is None and any(given(args, o) for o in ("score_threshold", "nms_iou", "max_detections")):
        raise PopcodeError("--score-threshold, --nms-iou and --max-detections set how --detector runs: add "
                           "--detector DET.onnx")
    if args.detector is not None and args.crop_origin is not None:
        raise PopcodeError("--crop-origin places a crop of a frame; --detector looks at whole camera frames")
    if args.detector is not None and args.obj_id:
        raise PopcodeError("--obj-id names the object in each --box; the detector names the objects it finds")
    if args.box is not None and len(args.box) > MAX_BOXES_PER_CALL:
        raise PopcodeError(f"{len(args.box)} boxes; the limit is {MAX_BOXES_PER_CALL} per call")
    if args.max_pixels < 1:
        raise PopcodeError(f"--max-pixels must be positive, got {args.max_pixels}")


def _check_bench(args: argparse.Namespace) -> None:
    if args.batch is None:
        args.batch = list(DEFAULT_BENCH_BATCHES)
    if min(args.batch) < 1 or args.iterations < 1 or args.warmup < 0:
        raise PopcodeError("batch sizes and iterations must be positive, warmup non-negative")
    if max(args.batch) > MAX_BENCH_BATCH:
        raise PopcodeError(f"--batch {max(args.batch)} is more than the limit of {MAX_BENCH_BATCH}")


def _check_detect(args: argparse.Namespace) -> None:
    if (args.image is None) == (args.split is None):
        raise PopcodeError("give an IMAGE to detect in, or a --split of images (then also --out JSON), one of the "
                           "two")
    if args.split is not None and args.out is None:
        raise PopcodeError("--split writes its detections to a file: add --out JSON")
    if args.json and args.split is not None:
        raise PopcodeError("--json prints one IMAGE's boxes; a --split's detections are written to --out as JSON")
    if args.max_images is not None and args.max_images < 1:
        raise PopcodeError(f"--max-images must be at least 1, got {args.max_images}")
    if args.max_pixels < 1:
        raise PopcodeError(f"--max-pixels must be positive, got {args.max_pixels}")


def _check_run(args: argparse.Namespace) -> None:
    if args.max_images is not None and args.max_images < 1:
        raise PopcodeError(f"--max-images must be at least 1, got {args.max_images}")
    if not 0.0 <= args.min_visib_fract <= 1.0:
        raise PopcodeError(f"--min-visib-fract must lie in [0, 1], got {args.min_visib_fract}")


def _check_bag(args: argparse.Namespace) -> None:
    if args.every < 1:
        raise PopcodeError(f"--every must be at least 1, got {args.every}")
    if not (math.isfinite(args.start) and args.start >= 0.0):
        raise PopcodeError(f"--start must be a non-negative number of seconds, got {args.start}")
    if args.end is not None and not (math.isfinite(args.end) and args.end > args.start):
        raise PopcodeError(f"--end must be a number of seconds after --start ({args.start:g}), got {args.end}")
    if args.refine and args.depth_topic is None:
        raise PopcodeError("--refine refines the pose against the depth: add --depth-topic TOPIC")
    if args.detections_topic == args.poses_topic:
        raise PopcodeError(f"--detections-topic and --poses-topic are both {args.poses_topic}: one topic a type")


CHECKS = {"predict": _check_predict, "bench": _check_bench, "run": _check_run, "detect": _check_detect,
          "bag": _check_bag}
