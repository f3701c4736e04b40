"""``popcode-train export``: checkpoint -> ONNX model for the runtime, checked and optionally quantised."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError, first_line
from popcode_runtime.base.files import OVERWRITE_HELP, check_output_file
from popcode_runtime.base.output_lock import OutputLock
from popcode_runtime.coding.confidence import DEFAULT_THRESHOLD_DEG

from ..export.confidence_fit import calibrate_checkpoint
from ..export.model_io import trained_model
from ..export.onnx_export import COREML_MAX_DIM, export_trained
from ..export.quantise import QUANTISATIONS, quantised_path
from ..train import checkpoint
from ..train.config import Config

if TYPE_CHECKING:  # the data side is imported only when the default crops need it
    from ..train.training_data import TrainingSplit


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "export", help="export a checkpoint to ONNX",
        description="Write an ONNX model (input 'image', output 'code', metadata inside), check it against "
                    "torch on crops, and optionally write quantised copies beside it.")
    parser.add_argument("checkpoint", type=Path, help="a checkpoint written by 'popcode-train train' (last.pt)")
    parser.add_argument("--out", type=Path, required=True, help="path of the float ONNX model")
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    parser.add_argument("--quantize", nargs="+", choices=QUANTISATIONS, default=[], metavar="KIND",
                        help=f"also write quantised models: {', '.join(QUANTISATIONS)}")
    parser.add_argument("--split-output", type=int, default=0, metavar="COLUMNS",
                        help=f"compute the output layer in column blocks of at most COLUMNS outputs "
                             f"(use {COREML_MAX_DIM} for onnxruntime's CoreML provider on Apple M1)")
    parser.add_argument("--crops", type=Path,
                        help="crops for the parity check and int8 calibration, a .npy float32 [N, 1, 128, 128] "
                             "in [0, 1] (default: validation crops of the checkpoint's data)")
    parser.add_argument("--crop-obj-ids", type=Path, metavar="NPY",
                        help="the object id of each of --crops, a .npy of N integers; picks each crop's symmetries "
                             "for the pose agreement (needed for a model of objects with different symmetries)")
    parser.add_argument("--confidence-threshold", type=float, default=DEFAULT_THRESHOLD_DEG, metavar="DEG",
                        help=f"the calibrated confidence is P(rotation error < DEG), fitted on the images the "
                             f"checkpoint's training held out (default {DEFAULT_THRESHOLD_DEG:g})")
    parser.add_argument("--no-confidence", action="store_true",
                        help="export without a confidence calibrator (the runtime then reports confidence null)")
    parser.set_defaults(handler=run)


def _load_npy(path: Path, what: str) -> np.ndarray:
    if not path.is_file():
        raise PopcodeError(f"{what} file not found: {path}")
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:  # not .npy, or an object array that needs pickle
        raise PopcodeError(f"{what} {path} is not a .npy array of numbers: {first_line(error)}") from error
    if not isinstance(array, np.ndarray):  # an .npz archive
        raise PopcodeError(f"{what} {path} is an .npz archive; save one array with numpy.save")
    return array


def _check_crops(crops: np.ndarray, obj_ids: np.ndarray | None) -> None:
    """Parity and calibration crops must be what the runtime feeds the model: finite, in [0, 1], [N, 1, S, S]."""
    if crops.ndim != 4 or crops.shape[1] != 1 or len(crops) == 0 or not np.issubdtype(crops.dtype, np.floating):
        raise PopcodeError(f"--crops must be float [N >= 1, 1, S, S], got {crops.dtype} {crops.shape}")
    if not np.isfinite(crops).all():
        raise PopcodeError("--crops contains NaN or inf: no agreement can be judged on them")
    if crops.min() < 0.0 or crops.max() > 1.0:
        raise PopcodeError(f"--crops must lie in [0, 1], got [{crops.min():.3g}, {crops.max():.3g}]")
    if obj_ids is not None and (obj_ids.shape != (len(crops),) or not np.issubdtype(obj_ids.dtype, np.integer)):
        raise PopcodeError(f"--crop-obj-ids must be {len(crops)} integers, got {obj_ids.dtype} {obj_ids.shape}")


def _crops(args: argparse.Namespace,
           state: dict[str, Any]) -> tuple[np.ndarray, np.ndarray | None, TrainingSplit | None]:
    """Parity crops and their object ids (None: not given); by default the validation crops of the checkpoint's
    training (``state``: its contents), with its training split, read once for the calibration too."""
    if args.crops is not None:
        obj_ids = None if args.crop_obj_ids is None else _load_npy(args.crop_obj_ids, "crop object ids")
        crops = _load_npy(args.crops, "crops")
        _check_crops(crops, obj_ids)
        return crops, obj_ids, None
    if args.crop_obj_ids is not None:
        raise PopcodeError("--crop-obj-ids names the objects of --crops; give --crops too")
    from ..train.training_data import read_training_split, validation_crops  # the data side only when needed

    config = Config.from_dict(state["config"])
    split = read_training_split(config)
    return *validation_crops(config, split=split), split


def _percent(share: float | None) -> str:
    return "n/a" if share is None else f"{100 * share:.1f}%"


def run(args: argparse.Namespace) -> int:
    inputs = [args.checkpoint, *filter(None, [args.crops, args.crop_obj_ids])]
    for path in [args.out, *(quantised_path(args.out, kind) for kind in args.quantize)]:
        check_output_file(path, "--out", inputs, args.overwrite)
    lock = args.out.with_name(f"{args.out.name}.lock")  # beside the float model: one for it and its quantised copies
    with OutputLock(lock, f"another popcode-train export is writing {args.out} (it holds {lock.name}); wait for it "
                          "to end, or give another --out"):
        state = checkpoint.load_trained(args.checkpoint)  # read once, and refused here before any crop is read
        crops, obj_ids, split = _crops(args, state)
        trained = trained_model(state, args.checkpoint)
        calibrator, note = (None, "not asked for (--no-confidence)") if args.no_confidence else \
            calibrate_checkpoint(trained, args.confidence_threshold, split=split)
        results = export_trained(trained, args.out, crops, tuple(args.quantize), args.split_output,
                                 obj_ids=obj_ids, calibrator=calibrator)
    print(f"{'model':<50} {'max abs diff':>14} {'argmax agreement':>17} {'pose agreement':>15}")
    for result in results:
        print(f"{str(result.path):<50} {result.max_abs_diff:>14.3g} {_percent(result.argmax_agreement):>17} "
              f"{_percent(result.pose_agreement):>15}")
    print("pose agreement: the same decoded rotation up to the object's symmetries, within one grid step "
          "(the argmax may differ between the equivalent peaks of a symmetric object)")
    if any(result.pose_agreement is None for result in results):
        print("pose agreement n/a: the model's objects differ in symmetry; give the object of each crop "
              "(--crop-obj-ids)")
    print(f"confidence calibrator: {note}" if calibrator else f"no confidence calibrator: {note}")
    return 0
