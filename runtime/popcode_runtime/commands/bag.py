"""The ``popcode bag`` command line: a ROS 2 bag's camera frames -> a bag of ``vision_msgs/Detection3DArray`` and
``geometry_msgs/PoseArray``, each frame through :class:`~popcode_runtime.inference.frame.FramePoseEstimator`, as
``popcode predict --detector`` poses one image (docs/runtime.md#popcode-bag)."""

from __future__ import annotations

import argparse
import math
import time
from collections import Counter
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path

from ..base.errors import PopcodeError
from ..base.files import check_output_file
from ..base.output_lock import OutputLock
from ..inference.estimator import PoseEstimator
from ..inference.frame import FramePoseEstimator
from ..model.decoding import DECODERS
from ..ros.bag_input import BagFrames, Topics, open_bag
from ..ros.bag_output import STORAGES, BagOutput, check_bag_output
from ..ros.foxglove_scene import FoxgloveOutput
from ..ros.library import INSTALL_HINT
from .detect import add_detector_options, open_detector, skipped_line
from .run_loop import Progress

DEFAULT_DETECTIONS_TOPIC, DEFAULT_POSES_TOPIC = "/popcode/detections", "/popcode/poses"


def register(commands: argparse._SubParsersAction, add_runtime_options: Callable[[argparse.ArgumentParser], None],
             ) -> None:
    bag = commands.add_parser(
        "bag", help="every part's pose in each frame of a ROS 2 bag -> a bag of vision_msgs/Detection3DArray",
        description="Read a rosbag2 (MCAP or SQLite3): the images of --image-topic, each with the CameraInfo "
                    "received before it (and the depth image of its stamp with --depth-topic); find the parts with "
                    "the detector, pose each with the model of its object, and write a new rosbag2 with a "
                    "vision_msgs/Detection3DArray and a geometry_msgs/PoseArray per frame (the image's header; "
                    f"metres, quaternions). Needs {INSTALL_HINT}.")
    bag.add_argument("models", nargs="+", type=Path, metavar="MODEL",
                     help="popcode ONNX model(s); each box goes to the model that knows its object")
    bag.add_argument("--bag", type=Path, required=True, metavar="IN",
                     help="the recorded bag: a rosbag2 folder, or its .mcap or .db3 file")
    bag.add_argument("--detector", type=Path, required=True, metavar="DET.onnx", help="popcode detector")
    add_detector_options(bag)
    bag.add_argument("--image-topic", required=True, metavar="TOPIC",
                     help="sensor_msgs/Image (mono8, mono16, rgb8, bgr8) or sensor_msgs/CompressedImage")
    bag.add_argument("--camera-info-topic", required=True, metavar="TOPIC", help="sensor_msgs/CameraInfo of the images")
    bag.add_argument("--depth-topic", metavar="TOPIC",
                     help="registered depth, sensor_msgs/Image 16UC1 (mm) or 32FC1 (m): the translation from the "
                          "observed surface instead of the box")
    bag.add_argument("--refine", action="store_true",
                     help="with --depth-topic: refine rotation and translation against the depth (needs "
                          "pip install ./runtime[depth])")
    bag.add_argument("--out", type=Path, required=True, metavar="OUT", help="the rosbag2 folder to write")
    bag.add_argument("--foxglove", type=Path, metavar="FILE.mcap",
                     help="also write the frames, their camera and every part's box and axes at its pose as an MCAP "
                          "of Foxglove's schemas, to open in Foxglove")
    bag.add_argument("--storage", choices=STORAGES, default=STORAGES[0], help="the output bag's storage (default mcap)")
    bag.add_argument("--detections-topic", default=DEFAULT_DETECTIONS_TOPIC, metavar="TOPIC",
                     help=f"where the Detection3DArray go (default {DEFAULT_DETECTIONS_TOPIC})")
    bag.add_argument("--poses-topic", default=DEFAULT_POSES_TOPIC, metavar="TOPIC",
                     help=f"where the PoseArray go (default {DEFAULT_POSES_TOPIC})")
    bag.add_argument("--every", type=int, default=1, metavar="N", help="every N-th image only (default 1: all)")
    bag.add_argument("--start", type=float, default=0.0, metavar="S", help="from S seconds after the bag's start")
    bag.add_argument("--end", type=float, metavar="S", help="up to S seconds after the bag's start")
    bag.add_argument("--decoder", choices=DECODERS, default="argmax",
                     help="argmax: the paper's winning neuron (default); refined: sub-neuron estimate")
    bag.add_argument("--overwrite", action="store_true",
                     help="replace a bag at --out and a file at --foxglove (never an input)")
    bag.add_argument("--quiet", action="store_true", help="no progress line")
    add_runtime_options(bag)
    bag.set_defaults(handler=handle)


def handle(args: argparse.Namespace) -> int:
    inputs = [args.bag, args.detector, *args.models]
    out = check_bag_output(args.out, inputs, args.overwrite)
    if args.foxglove is not None:
        check_output_file(args.foxglove, "--foxglove", [*inputs, out], args.overwrite)
    busy = f"another popcode bag is writing {out}; wait for it or choose another --out"
    started = time.perf_counter()
    with OutputLock(out.with_name(out.name + ".lock"), busy), open_bag(args.bag) as reader:
        frames = BagFrames(reader, Topics(args.image_topic, args.camera_info_topic, args.depth_topic), args.bag)
        estimators = [PoseEstimator(path, providers=args.provider, threads=args.threads, decoder=args.decoder)
                      for path in args.models]
        estimator = FramePoseEstimator(open_detector(args), estimators, [str(path) for path in args.models])
        objects = {obj_id: info for e in estimators for obj_id, info in e.metadata.objects.items()}
        bar = Progress(math.ceil(frames.image_count / args.every), not args.quiet, "popcode bag")
        skipped: Counter[int] = Counter()
        estimates = 0
        scene = nullcontext(None) if args.foxglove is None else FoxgloveOutput(args.foxglove, objects)
        with BagOutput(out, args.storage, args.detections_topic, args.poses_topic, objects) as output, scene as view:
            for frame in frames.frames(args.every, args.start, args.end):
                poses = estimator.estimate(frame.image, K=frame.K, depth=frame.depth, depth_scale=frame.depth_scale,
                                           refine_depth=args.refine)
                output.add(frame, poses)
                if view is not None:
                    view.add(frame, poses)
                skipped.update(estimator.last_skipped)
                estimates += len(poses)
                bar.step()
            if not output.frames:
                raise PopcodeError(f"no images on {args.image_topic} in {args.bag}"
                                   + ("" if args.start == 0.0 and args.end is None else " between --start and --end")
                                   + ": nothing to estimate")
            output.finish()
    print(f"wrote {out}: {estimates} estimates of {output.frames} frames on {args.detections_topic} and "
          f"{args.poses_topic} in {time.perf_counter() - started:.1f} s"
          + ("" if args.foxglove is None else f"; {args.foxglove} for Foxglove"))
    if skipped:
        print(skipped_line(skipped))
    return 0
