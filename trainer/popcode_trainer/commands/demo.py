"""``popcode-train demo``: the whole product on the built-in objects or a user's parts, into one run folder."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import refuse_inputs

from ..data.render import MAX_RENDERED_IMAGES
from ..demo.files import REPORT_FILE
from ..demo.parts import BUILTIN
from ..demo.run import describe_parts, prepare_parts, run_demo
from ..demo.sizes import DEMO_SIZES, HIDDEN_SIZES, SMOKE_LATENCY_ITERATIONS
from ..train.config import MAX_EPOCHS
from ..train.pretrained import NONE


def register(subparsers: argparse._SubParsersAction) -> None:
    sizes = "; ".join(f"{name}: {size.purpose}" for name, size in DEMO_SIZES.items())
    parser = subparsers.add_parser(
        "demo", help="render, train, export, evaluate and benchmark on the built-in objects or your own parts",
        description="Render the six built-in parts (or the parts of a BOP models folder, --objects), train the "
                    "population code and the single-variable baseline with the same network and budget, one model "
                    "per object group (parts with a continuous symmetry about one axis together, the others "
                    "together; a user's parts that need different codes apart), export ONNX (float and int8), "
                    "evaluate both with the BOP metrics through the runtime, time the runtime, and write "
                    f"{REPORT_FILE} with tables and figures. A models folder is checked before anything is "
                    "rendered. Rerun with the same --out to resume an interrupted demo; a second demo on the same "
                    "--out is refused while the first runs.")
    parser.add_argument("--objects", default=BUILTIN, metavar="MODELS",
                        help="'builtin' (default: the six built-in parts) or a BOP models folder with "
                             "models_info.json and obj_XXXXXX.ply meshes in millimetres")
    parser.add_argument("--check", action="store_true",
                        help="check --objects, print the object groups and the code each trains with, and stop")
    parser.add_argument("--size", choices=[*DEMO_SIZES, *HIDDEN_SIZES], default="quick",
                        metavar="{" + ",".join(DEMO_SIZES) + "}", help=f"budget ({sizes})")
    parser.add_argument("--out", type=Path, default=Path("runs/demo"), help="run folder (default: runs/demo)")
    parser.add_argument("--epochs", type=int, help="train this many epochs instead of fitting them to the size's "
                                                   f"time budget (quick: {DEMO_SIZES['quick'].minutes:g} min) or "
                                                   "taking the size's")
    parser.add_argument("--minutes", type=float, metavar="M",
                        help="fit the epochs so the whole demo takes about M minutes on this machine "
                             "(every model trains one epoch, then as many as fit)")
    parser.add_argument("--images", type=int, metavar="N", help="training images per object instead of the size's")
    parser.add_argument("--from-scratch", action="store_true",
                        help="start every model and the detector from random weights, not from the shipped "
                             "pretrained start of its network (popcode-train pretrain) and the shipped detector start")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    demo = {**DEMO_SIZES, **HIDDEN_SIZES}[args.size]
    size, minutes = demo.pipeline, demo.minutes
    for option, value, most in (("--epochs", args.epochs, MAX_EPOCHS), ("--images", args.images, MAX_RENDERED_IMAGES),
                                ("--minutes", args.minutes, math.inf)):
        if value is not None and not (value >= 1 and math.isfinite(value)):
            raise PopcodeError(f"{option} must be at least 1 and finite, got {value}")
        if value is not None and value > most:
            raise PopcodeError(f"{option} must be at most {most:,}, got {value:,}")
    if args.epochs is not None and args.minutes is not None:
        raise PopcodeError("--epochs and --minutes both set the training budget; give one")
    if args.check:
        print(describe_parts(*prepare_parts(args.objects, size.config.code)))
        return 0
    if args.objects != BUILTIN:
        refuse_inputs(args.out, "--out", [args.objects])
    if args.epochs is not None:
        size, minutes = size.with_epochs(args.epochs), None
    if args.minutes is not None:
        minutes = args.minutes
    if args.images is not None:
        size = dataclasses.replace(size, train_images_per_object=args.images)
    if args.from_scratch:
        size = size.with_init(NONE)
    latency_iterations = SMOKE_LATENCY_ITERATIONS if args.size in HIDDEN_SIZES else 50
    run_demo(args.size, args.out, size, latency_iterations=latency_iterations, minutes=minutes, objects=args.objects)
    return 0
