"""``popcode-train demo``: the whole product on the built-in objects, into one run folder."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from popcode_runtime.errors import PopcodeError

from ..demo.report import REPORT_FILE
from ..demo.run import DEMO_SIZES, run_demo


def register(subparsers: argparse._SubParsersAction) -> None:
    sizes = "; ".join(f"{name}: {size.purpose}" for name, size in DEMO_SIZES.items())
    parser = subparsers.add_parser(
        "demo", help="render, train, export, evaluate and benchmark on the built-in objects",
        description="Render the six built-in parts, train the population code and the single-variable baseline "
                    "with the same network and budget, export ONNX (float and int8), evaluate both with the BOP "
                    f"metrics through the runtime, time the runtime, and write {REPORT_FILE} with tables and "
                    "figures. Rerun with the same --out to resume an interrupted demo.")
    parser.add_argument("--size", choices=list(DEMO_SIZES), default="quick", help=f"budget ({sizes})")
    parser.add_argument("--out", type=Path, default=Path("runs/demo"), help="run folder (default: runs/demo)")
    parser.add_argument("--epochs", type=int, help="train this many epochs instead of fitting them to the size's "
                                                   f"time budget (quick: {DEMO_SIZES['quick'].minutes:g} min) or "
                                                   "taking the size's")
    parser.add_argument("--minutes", type=float, metavar="M",
                        help="fit the epochs so the whole demo takes about M minutes on this machine "
                             "(every model trains one epoch, then as many as fit)")
    parser.add_argument("--images", type=int, metavar="N", help="training images per object instead of the size's")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    demo = DEMO_SIZES[args.size]
    size, minutes = demo.pipeline, demo.minutes
    for option, value in (("--epochs", args.epochs), ("--images", args.images), ("--minutes", args.minutes)):
        if value is not None and not (value >= 1 and math.isfinite(value)):
            raise PopcodeError(f"{option} must be at least 1 and finite, got {value}")
    if args.epochs is not None and args.minutes is not None:
        raise PopcodeError("--epochs and --minutes both set the training budget; give one")
    if args.epochs is not None:
        size, minutes = size.with_epochs(args.epochs), None
    if args.minutes is not None:
        minutes = args.minutes
    if args.images is not None:
        size = dataclasses.replace(size, train_images_per_object=args.images)
    run_demo(args.size, args.out, size, minutes=minutes)
    return 0
