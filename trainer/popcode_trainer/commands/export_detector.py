"""``popcode-train export-detector``: a detector checkpoint -> the ONNX file the runtime's ``Detector`` runs."""

from __future__ import annotations

import argparse
from pathlib import Path

from popcode_runtime.base.files import OVERWRITE_HELP, check_output_file


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export-detector", help="export a detector checkpoint to ONNX",
        description="Write the network and its box decoding as ONNX with the detector's metadata (objects, input "
                    "size, default thresholds, training); onnxruntime must agree with torch on it.")
    parser.add_argument("checkpoint", type=Path, help="detector.pt of a train-detector run")
    parser.add_argument("--out", required=True, type=Path, metavar="FILE.onnx", help="detector file to write")
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    check_output_file(args.out, "--out", [args.checkpoint], args.overwrite)
    from ..detection.export import export_detector

    print(f"wrote {export_detector(args.checkpoint, args.out)}")
    return 0
