"""The ``popcode-train`` command. Each subcommand lives in ``popcode_trainer.commands.<name>``
and provides ``register(subparsers)``, which adds its parser and sets ``handler``."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from popcode_runtime.commands.cli import run_handler
from popcode_runtime.commands.parser import CommandParser

from . import __version__

COMMAND_MODULES: tuple[str, ...] = (
    "render",
    "path_trace",
    "preview",
    "train",
    "pretrain",
    "export",
    "evaluate",
    "detections",
    "evaluate_detections",
    "train_detector",
    "export_detector",
    "demo",
    "kit",
)


def build_parser() -> argparse.ArgumentParser:
    parser = CommandParser(
        prog="popcode-train", description="Render data, train, evaluate and export population-code networks."
    )
    parser.add_argument("--version", action="version", version=f"popcode-trainer {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(f"popcode_trainer.commands.{name}").register(commands)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; bad input ends with one line on stderr and exit code 2."""
    return run_handler(build_parser().parse_args(argv), "popcode-train")


if __name__ == "__main__":
    sys.exit(main())
