"""``popcode-train export``: checkpoint -> ONNX model for the runtime, checked and optionally quantised."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from popcode_runtime.errors import PopcodeError

from .. import checkpoint
from ..config import Config
from ..export import COREML_MAX_DIM, QUANTISATIONS, export_checkpoint


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export", help="export a checkpoint to ONNX",
        description="Write an ONNX model (input 'image', output 'code', metadata inside), check it against "
                    "torch on crops, and optionally write quantised copies beside it.")
    parser.add_argument("checkpoint", type=Path, help="a checkpoint written by 'popcode-train train' (last.pt)")
    parser.add_argument("--out", type=Path, required=True, help="path of the float ONNX model")
    parser.add_argument("--quantize", nargs="+", choices=QUANTISATIONS, default=[], metavar="KIND",
                        help=f"also write quantised models: {', '.join(QUANTISATIONS)}")
    parser.add_argument("--split-output", type=int, default=0, metavar="COLUMNS",
                        help=f"compute the output layer in column blocks of at most COLUMNS outputs "
                             f"(use {COREML_MAX_DIM} for onnxruntime's CoreML provider on Apple M1)")
    parser.add_argument("--crops", type=Path,
                        help="crops for the parity check and int8 calibration, a .npy float32 [N, 1, 128, 128] "
                             "in [0, 1] (default: validation crops of the checkpoint's data)")
    parser.set_defaults(handler=run)


def _crops(args: argparse.Namespace) -> np.ndarray:
    if args.crops is not None:
        if not args.crops.is_file():
            raise PopcodeError(f"crops file not found: {args.crops}")
        return np.load(args.crops, allow_pickle=False)
    from ..training_data import validation_crops  # imports the data side only when needed

    return validation_crops(Config.from_dict(checkpoint.load(args.checkpoint)["config"]))


def run(args: argparse.Namespace) -> int:
    results = export_checkpoint(args.checkpoint, args.out, _crops(args), tuple(args.quantize), args.split_output)
    print(f"{'model':<50} {'max abs diff':>14} {'argmax agreement':>17}")
    for result in results:
        print(f"{str(result.path):<50} {result.max_abs_diff:>14.3g} {100 * result.argmax_agreement:>16.1f}%")
    return 0
