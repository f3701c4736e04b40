"""The ``popcode`` command: predict, info and bench on an ONNX popcode model; run over a BOP split; detect."""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable, Sequence

import cv2
import numpy as np

from .. import __version__
from ..base.errors import PopcodeError
from ..base.files import OVERWRITE_HELP, check_picture_path, write_picture_atomic
from ..depth.surface_fit import object_surface, read_depth
from ..geometry.camera import MAX_FIELD_OF_VIEW_DEG, MIN_FIELD_OF_VIEW_DEG, camera_for_image, parse_camera_matrix
from ..geometry.crop import MAX_IMAGE_PIXELS, read_image
from ..geometry.rotations import matrix_to_axis_angle
from ..geometry.symmetries import symmetry_class
from ..inference.benchmark import benchmark_estimator, machine_description
from ..inference.detector import Detector, is_detector_file
from ..inference.estimator import PoseEstimator
from ..inference.frame import FramePoseEstimator
from ..inference.prediction import Prediction
from ..model.decoding import DECODERS
from ..model.detector_metadata import PREFIX as DETECTOR_PREFIX
from . import bag as bag_command
from . import detect as detect_command
from . import run as run_command
from .detect import add_detector_options, open_detector, skipped_line
from .drawing import draw_models
from .options import DEFAULT_BENCH_BATCHES, check_options
from .parser import CommandParser

INFO_VALUE_WIDTH = 100  # characters of one training value in ``info``'s text output
NUMBER_OPTIONS = ("--box", "--K", "--crop-origin")  # their values may start with a minus sign


def _numbers(text: str, count: int | None, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.replace(" ", "").split(",")]
    except ValueError as error:
        raise argparse.ArgumentTypeError(f"{what} must be comma-separated numbers, got {text!r}") from error
    if count is not None and len(values) != count:
        raise argparse.ArgumentTypeError(f"{what} needs {count} numbers, got {len(values)} in {text!r}")
    return values


def _box(text: str) -> list[float]:
    return _numbers(text, 4, "--box X,Y,W,H")


def _camera(text: str) -> list[float]:
    return _numbers(text, None, "--K fx,fy,cx,cy")


def _point(text: str) -> list[float]:
    return _numbers(text, 2, "--crop-origin X,Y")


def _add_runtime_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--provider", action="append", metavar="NAME",
                        help="execution provider: cpu (default), cuda, coreml, ...; repeat for a preference order")
    parser.add_argument("--threads", type=int, default=0, help="intra-op threads (0: all cores, the default)")


def _predict(args: argparse.Namespace) -> int:
    if args.draw:
        # before the model runs: a typo costs a line, not the run
        check_picture_path(args.draw, "--draw", [*args.models, args.image, *filter(None, [args.depth])],
                           args.overwrite)
    estimators = [PoseEstimator(path, providers=args.provider, threads=args.threads, decoder=args.decoder)
                  for path in args.models]
    frame = FramePoseEstimator(open_detector(args), estimators, list(map(str, args.models))) if args.detector \
        else None
    image = read_image(args.image, args.max_pixels)
    depth = read_depth(args.depth, args.max_pixels) if args.depth else None
    K = parse_camera_matrix(args.K) if args.K else None
    options = {"K": K, "return_code": args.code, "top_k": args.top_k, "translation": args.translation,
               "depth": depth, "depth_scale": 1.0 if args.depth_scale is None else args.depth_scale,
               "refine_depth": args.refine}
    if frame is not None:
        poses = frame.estimate(image, **options)
        predictions, detections = [pose.prediction for pose in poses], [pose.detection for pose in poses]
        skipped = frame.last_skipped
    else:
        predictions = estimators[0].predict(image, args.box, obj_ids=args.obj_id, crop_origin=args.crop_origin,
                                            **options)
        detections, skipped = [None] * len(predictions), {}
    if args.draw:
        camera = None if K is None else camera_for_image(K, image.shape, args.crop_origin)  # in the image's pixels
        drawn = [(e.metadata, [p for p in predictions if p.obj_id is None or p.obj_id in e.metadata.objects])
                 for e in estimators]
        write_picture_atomic(args.draw, draw_models(image, drawn, camera))
    if args.json:
        print(json.dumps({"models": list(map(str, args.models)), "image": str(args.image),
                          "predictions": [{**p.to_dict(), **({} if d is None else {"detection": d.to_dict()})}
                                          for p, d in zip(predictions, detections, strict=True)],
                          **({} if frame is None else {"skipped_detections": {str(k): v for k, v in skipped.items()}})},
                         indent=2))
        return 0
    np.set_printoptions(precision=4, suppress=True)
    if frame is not None and not predictions:
        known = sorted(obj_id for estimator in estimators for obj_id in estimator.metadata.objects)
        print(f"no parts of objects {known} found", file=sys.stderr)
    for index, (prediction, detection) in enumerate(zip(predictions, detections, strict=True)):
        axis = ", ".join(f"{v:+.3f}" for v in prediction.axis)
        found = "" if detection is None else f"object {detection.obj_id} detected (score {detection.score:.3f}) in "
        print(f"{found}box {index} {[round(v, 1) for v in prediction.box]}: angle "
              f"{np.degrees(prediction.angle_rad):.1f} deg about ({axis}), score {prediction.score:.3f}")
        for row in prediction.R_m2c:
            print("    " + "  ".join(f"{v:+.4f}" for v in row))
        if prediction.t_m2c_mm is not None:
            print("    t_m2c_mm " + "  ".join(f"{v:+.1f}" for v in prediction.t_m2c_mm) + _source_text(prediction))
        for rank, hypothesis in enumerate(prediction.hypotheses or []):
            axis, angle = matrix_to_axis_angle(hypothesis.R_m2c)
            print(f"    hypothesis {rank}: score {hypothesis.score:.2f}, activation {hypothesis.activation:.3f}, "
                  f"angle {np.degrees(angle):.1f} deg about ({', '.join(f'{v:+.3f}' for v in axis)}), "
                  f"{len(hypothesis.equivalent)} equivalent peak(s)")
    if skipped:
        print(skipped_line(skipped))
    return 0


def _source_text(prediction: Prediction) -> str:
    """Where a translation came from, its depth fit and any note, as printed after it."""
    details = [] if prediction.depth_fit is None else [f"depth fit {prediction.depth_fit:.2f}"]
    details += [] if prediction.depth_note is None else [prediction.depth_note]
    return f"  ({prediction.t_source}{': ' if details else ''}{'; '.join(details)})"


def _info(args: argparse.Namespace) -> int:
    if is_detector_file(args.model):
        return _detector_info(args)
    estimator = PoseEstimator(args.model)
    meta = estimator.metadata
    if args.json:
        print(json.dumps({"model": str(args.model), "providers": estimator.providers,
                          "output_dim": meta.output_dim, **{k: json.loads(v) for k, v in meta.to_props().items()}},
                         indent=2))
        return 0
    code = meta.code
    layout = (f"{code.n_axes} axes (axis-only, symmetry axis {list(code.symmetry_axis)})" if code.axis_only
              else f"{code.n_axes} axes x {code.n_angles} angles")
    print(f"model            {args.model}")
    print(f"representation   {meta.representation} ({meta.output_dim} outputs per crop)")
    print(f"code             {layout}, sigma {code.sigma_deg:g} deg, {code.lattice} lattice")
    print(f"rotation frame   {meta.rotation_frame}")
    print(f"input            {meta.input_size}x{meta.input_size} grey crop, padding {meta.crop_padding:g}")
    for obj_id, info in sorted(meta.objects.items()):
        diameter = info.get("diameter")
        size = f", diameter {diameter:.1f} mm" if isinstance(diameter, (int, float)) else ""
        surface = object_surface(info)
        depth = f", {len(surface.points_mm)} surface points for depth" if surface else ", no surface points for depth"
        print(f"object {obj_id:<9} symmetry {symmetry_class(info).value}{size}{depth}")
    _print_training(meta.training)
    return 0


def _detector_info(args: argparse.Namespace) -> int:
    """``info`` of a detector file: its objects, input, default thresholds and what it was trained on."""
    detector = Detector(args.model)
    meta = detector.metadata
    if args.json:
        print(json.dumps({"model": str(args.model), "kind": "detector", "providers": detector.session.get_providers(),
                          **{k.removeprefix(DETECTOR_PREFIX): json.loads(v) for k, v in meta.to_props().items()}},
                         indent=2))
        return 0
    print(f"model            {args.model}")
    print("kind             detector (popcode detect, popcode run --detector, popcode predict --detector)")
    print(f"objects          {', '.join(map(str, meta.obj_ids))}")
    print(f"input            {meta.input_width}x{meta.input_height} grey frame (a frame of any size and aspect is "
          "letterboxed)")
    print(f"thresholds       score {meta.score_threshold:g}, NMS IoU {meta.nms_iou:g}, at most "
          f"{meta.max_detections} boxes")
    print(f"first weights    {_first_weights(meta.training)}")
    _print_training({k: v for k, v in meta.training.items() if k != "first_weights"})
    return 0


def _first_weights(training: dict[str, object]) -> str:
    """What a detector's training began from, a commit in it shortened to 12 digits (the line stays one line; the
    whole is in ``--json``). Detectors exported before detector starts existed say it only in their architecture
    line, "trained from scratch"."""
    if "first_weights" in training:
        return re.sub(r"\b([0-9a-f]{12})[0-9a-f]{28}\b", r"\1", str(training["first_weights"]))
    if "trained from scratch" in str(training.get("architecture", "")):
        return "random weights (trained from scratch)"
    return "not recorded"


def _print_training(training: dict[str, object]) -> None:
    """``info``'s ``training.*`` lines; a revision ending in ``+dirty`` is said in words."""
    for key, value in sorted(training.items()):
        dirty = key == "git_revision" and str(value).endswith("+dirty")
        note = " (exported from a tree with uncommitted changes beside that commit)" if dirty else ""
        print(f"training.{key:<8} {_short(value)}{note}")


def _short(value: object, width: int = INFO_VALUE_WIDTH) -> str:
    """A training value for one line of ``info``: long settings are named only, ``--json`` prints them."""
    if isinstance(value, float):
        return f"{value:.4g}"
    text = str(value)
    if len(text) <= width:
        return text
    if isinstance(value, dict):
        names = ", ".join(map(str, value))
        names = names if len(names) <= width - 40 else names[: width - 45].rsplit(",", 1)[0] + ", ..."
        return f"{len(value)} settings ({names}); --json prints them"
    return text[: width - 25] + " ... (--json prints all)"


def _bench(args: argparse.Namespace) -> int:
    estimator = PoseEstimator(args.model, providers=args.provider, threads=args.threads)
    stats = benchmark_estimator(estimator, args.batch, args.warmup, args.iterations, args.threads)
    if args.json:
        print(json.dumps({"model": str(args.model), "providers": estimator.providers,
                          "machine": machine_description(), "results": [s.to_dict() for s in stats]}, indent=2))
        return 0
    machine = machine_description()
    print(f"{args.model} on {machine['cpu']} ({machine['cores']} cores), {', '.join(estimator.providers)}, "
          f"threads {args.threads or 'all'}")
    print("| stage | batch | median ms | p90 ms | p99 ms | crops/s |")
    print("|---|---:|---:|---:|---:|---:|")
    for s in stats:
        print(f"| {s.stage} | {s.batch} | {s.median_ms:.2f} | {s.p90_ms:.2f} | {s.p99_ms:.2f} | {s.crops_per_s:.0f} |")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(prog="popcode", description="Object rotation from a neural population code.")
    parser.add_argument("--version", action="version", version=f"popcode-runtime {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    predict = commands.add_parser("predict", help="rotation of the object in each box of an image",
                                  description="Crop each box, run the model once on the batch, decode rotations; "
                                              "with --detector, every part of a camera frame, each box posed by the "
                                              "model of its object.")
    predict.add_argument("models", nargs="+", metavar="MODEL",
                         help="popcode ONNX model; with --detector every model of the frame's parts (each box goes "
                              "to the model that knows its object, boxes no model knows are counted)")
    predict.add_argument("image", help="image file (grey or colour, 8 or 16 bit)")
    predict.add_argument("--box", type=_box, action="append", metavar="X,Y,W,H",
                         help="object box in pixels (top-left corner, width, height); repeat for several objects "
                              "(or --detector)")
    predict.add_argument("--detector", metavar="DET.onnx",
                         help="find the model's objects with this popcode detector instead of --box")
    add_detector_options(predict)
    predict.add_argument("--K", type=_camera, metavar="FX,FY,CX,CY",
                         help="camera intrinsics (needed by allocentric models); fx,fy,cx,cy or 9 numbers row-major; "
                              f"checked against IMAGE (principal point on it, a field of view of "
                              f"{MIN_FIELD_OF_VIEW_DEG:g} to {MAX_FIELD_OF_VIEW_DEG:g} deg)")
    predict.add_argument("--crop-origin", type=_point, metavar="X,Y",
                         help="IMAGE is a crop of the frame --K belongs to, its top-left pixel at X,Y there (the "
                              "principal point is moved by it)")
    predict.add_argument("--decoder", choices=DECODERS, default="argmax",
                         help="argmax: the paper's winning neuron (default); refined: sub-neuron estimate")
    predict.add_argument("--top-k", type=int, default=1, metavar="K",
                         help="also list up to K distinct poses of the code (symmetric peaks merged)")
    predict.add_argument("--translation", action="store_true",
                         help="estimate the translation from the box too (needs --K)")
    predict.add_argument("--depth", metavar="PNG",
                         help="depth image registered to IMAGE (16-bit PNG; 0: no reading): the translation from the "
                              "object's observed surface instead of the box (needs --K)")
    predict.add_argument("--depth-scale", type=float, metavar="S",
                         help="mm per depth unit, as BOP's depth_scale (default 1)")
    predict.add_argument("--refine", action="store_true",
                         help="with --depth: also refine rotation and translation against the observed points "
                              "(ICP; needs pip install ./runtime[depth]) from the code's three strongest poses "
                              "(or --top-k's), keeping the best fit")
    predict.add_argument("--obj-id", type=int, action="append", metavar="ID",
                         help="object id of each box, in order (for models of several objects)")
    predict.add_argument("--draw", metavar="PICTURE",
                         help="also write the (grey) image with each estimate drawn (box, axes, hull outline with "
                              "--translation, object id and confidence) to PICTURE (.png, .jpg, ...)")
    predict.add_argument("--overwrite", action="store_true", help=f"--draw: {OVERWRITE_HELP}")
    predict.add_argument("--json", action="store_true", help="print JSON instead of text")
    predict.add_argument("--code", action="store_true", help="include the raw network output (with --json)")
    predict.add_argument("--max-pixels", type=int, default=MAX_IMAGE_PIXELS, metavar="N",
                         help=f"refuse images of more pixels, before decoding them (default {MAX_IMAGE_PIXELS})")
    _add_runtime_options(predict)
    predict.set_defaults(handler=_predict)

    info = commands.add_parser("info", help="what a model's (or a detector's) metadata says",
                               description="Check a model and print its representation, code, objects and training.")
    info.add_argument("model", help="popcode ONNX model or detector")
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.set_defaults(handler=_info)

    bench = commands.add_parser("bench", help="latency and throughput on this device",
                                description="Warm up, then time end-to-end (crop+inference+decode) and "
                                            "inference-only calls at each batch size.")
    bench.add_argument("model", help="popcode ONNX model")
    bench.add_argument("--batch", type=int, action="append", metavar="N",
                       help=f"batch size; repeat for several (default: {', '.join(map(str, DEFAULT_BENCH_BATCHES))})")
    bench.add_argument("--warmup", type=int, default=10, help="untimed calls first (default 10)")
    bench.add_argument("--iterations", type=int, default=100, help="timed calls per row (default 100)")
    bench.add_argument("--json", action="store_true", help="print JSON instead of a table")
    _add_runtime_options(bench)
    bench.set_defaults(handler=_bench)
    run_command.register(commands, _add_runtime_options)
    detect_command.register(commands, _add_runtime_options)
    bag_command.register(commands, _add_runtime_options)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; bad input ends with one line on stderr and exit code 2."""
    args = build_parser().parse_args(_attach_negative_values(sys.argv[1:] if argv is None else list(argv)))
    return run_handler(args, "popcode", check_options)


def _attach_negative_values(argv: list[str]) -> list[str]:
    """``--box -50,8,66,58`` as ``--box=-50,8,66,58``: argparse would read the value as an option."""
    result: list[str] = []
    index = 0
    while index < len(argv):
        token = argv[index]
        if token in NUMBER_OPTIONS and index + 1 < len(argv) and re.match(r"-[\d.]", argv[index + 1]):
            result.append(f"{token}={argv[index + 1]}")
            index += 2
            continue
        result.append(token)
        index += 1
    return result


def run_handler(args: argparse.Namespace, prog: str,
                check: Callable[[argparse.Namespace], None] | None = None) -> int:
    """Run ``check`` (the command's option rules), then ``args.handler``; a ``PopcodeError`` or a failing system
    call (``OSError``) becomes one line on stderr and exit code 2.

    A reader that stops early (``| head``) is not an error: the rest of the
    output is dropped quietly and the exit code is the shell's for SIGPIPE.
    OpenCV is kept from logging to stderr itself (a torn PNG's "readHeader"
    complaint): the line that follows says what went wrong.
    """
    opencv_log_level = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    try:
        if check is not None:
            check(args)
        return int(args.handler(args) or 0)
    except PopcodeError as error:
        print(f"{prog}: error: {' '.join(str(error).split())}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        _silence_stdout()
        return 141
    except OSError as error:  # a full disk, a read-only folder, a name too long: the system's words, one line
        where = f" {error.filename}" if error.filename else ""
        print(f"{prog}: error: cannot use{where}: {error.strerror or error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        return 130
    finally:
        cv2.utils.logging.setLogLevel(opencv_log_level)


def _silence_stdout() -> None:
    """Point stdout at /dev/null so that Python's flush at exit does not raise BrokenPipeError again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no real file descriptor (in-process tests capture stdout)
        pass


if __name__ == "__main__":
    sys.exit(main())
