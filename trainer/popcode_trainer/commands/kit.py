"""``popcode-train kit``: a user's models folder to a kit of pose models, detector, samples and card."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..demo.sizes import HIDDEN_SIZES
from ..kit.budget import MAX_HOURS, MIN_HOURS
from ..kit.run import BUDGET, KIT_FILE, run_kit


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "kit", help="one command from your models folder to a kit in the layout of models/: pose models, detector, "
                    "samples and a card with its scores",
        description="Check a BOP models folder, render its parts alone, in bin scenes and (with Mitsuba) path "
                    "traced, train one population-code model per object group and a detector to a time budget, "
                    "export them, score them on test splits of their own, and write KIT/ as the repository's "
                    "models/ is laid out: parts-<ids>.onnx, parts-detector.onnx, samples/ and a card README.md "
                    "with the scores, the machine and the command. The budget chooses the data sizes and recipe "
                    "(docs/training.md#kit). Rerun the same command to resume; the work lies in KIT/work.")
    parser.add_argument("--objects", required=True, metavar="MODELS",
                        help="a BOP models folder with models_info.json and obj_XXXXXX.ply meshes in millimetres "
                             "(or 'builtin')")
    parser.add_argument("--out", required=True, type=Path, metavar="KIT",
                        help=f"the kit folder: new, empty, or a kit this command started (its {KIT_FILE})")
    parser.add_argument("--hours", required=True, type=float, metavar="H",
                        help=f"the whole run's budget on this machine, {MIN_HOURS:g} to {MAX_HOURS:g} hours")
    parser.add_argument("--size", choices=[BUDGET, *HIDDEN_SIZES], default=BUDGET, help=argparse.SUPPRESS)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    run_kit(args.objects, args.out, args.hours, args.size)
    return 0
