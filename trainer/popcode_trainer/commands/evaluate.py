"""``popcode-train evaluate``: models + a BOP split -> per-instance errors and the paper's tables."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import (
    MAX_NAME_BYTES,
    OVERWRITE_HELP,
    check_output_file,
    check_writable_file,
    refuse_inputs,
    require_folder,
)
from popcode_runtime.base.output_lock import folder_lock
from popcode_runtime.bop.split import BOP19_MIN_VISIB_FRACT
from popcode_runtime.inference.request import MAX_TOP_K
from popcode_runtime.model.decoding import DECODERS
from popcode_runtime.model.engine import check_threads

from ..data.box_noise import BOX_NOISE_PRESETS, box_noise_preset
from ..eval.pipeline.depth_poses import depth_modes
from ..eval.pipeline.detector_boxes import with_detector_boxes
from ..eval.pipeline.evaluate import evaluate_models
from ..eval.pipeline.models import ARGMAX, methods_from_paths
from ..eval.pipeline.results_matching import ResultsMatching
from ..eval.pipeline.split import read_eval_split
from ..eval.reporting.report import report_files, write_report
from ..eval.reporting.sections import report_markdown

EVALUATE_LOCK = "evaluate.lock"  # held in --out while an evaluation writes its report there


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "evaluate", help="score models on a BOP split with the BOP rotation metrics",
        description="Rotation from each model, translation from the ground truth (the paper's protocol). Writes "
                    "per-instance errors (CSV), the per-object and with/without-ambiguity tables (markdown, JSON) "
                    "and, if asked, BOP19 results files (score: the calibrated confidence; time: the measured "
                    "seconds of each image's estimates). Models given the same --name form one method (e.g. one "
                    "model per object group). With --translation, full 6-D poses too: the translation fitted to "
                    "each box as the runtime does it; with --depth, also from each image's depth (and with --refine "
                    "refined against it) as popcode run --depth does it. With --box-noise, each crop from a "
                    "detector-like box (scored per box IoU too); with --top-k, population codes also by the best "
                    "of their top K hypotheses.")
    parser.add_argument("models", nargs="+", type=Path, metavar="MODEL",
                        help="a training checkpoint (.pt, run with torch), an ONNX model (run with the runtime) or a "
                             "BOP19 results file (.csv, e.g. from popcode run; scored rotation-only, matched to the "
                             "instances per image and object as the BOP toolkit does: a missed instance is wrong, "
                             "estimates beyond the instance count are ignored)")
    parser.add_argument("--split", dest="splits", action="append", required=True, type=Path, metavar="DIR",
                        help="BOP split folder with scene folders (repeatable)")
    parser.add_argument("--models-dir", type=Path, required=True,
                        help="folder with the object meshes obj_XXXXXX.ply and models_info.json")
    parser.add_argument("--name", dest="names", action="append", default=[], metavar="NAME",
                        help="table row of each MODEL, in order (repeatable; default: the file name)")
    parser.add_argument("--obj-ids", nargs="+", type=int, metavar="ID", help="evaluate only these objects")
    parser.add_argument("--decoder", dest="decoders", nargs="+", choices=DECODERS, default=[ARGMAX],
                        metavar="DECODER",
                        help=f"how a population code becomes a rotation: {', '.join(DECODERS)} (default: argmax, "
                             "the paper's). Several score each population-code method once per decoder, as NAME "
                             "(argmax) and NAME (DECODER); other models once, with a warning")
    parser.add_argument("--out", type=Path, default=Path("eval"), help="output folder (default: ./eval)")
    parser.add_argument("--overwrite", action="store_true",
                        help=f"replace the report in --out if one is there ({OVERWRITE_HELP})")
    parser.add_argument("--bop19-csv", action="store_true", help="also write a BOP19 results CSV per method")
    parser.add_argument("--translation", action="store_true",
                        help="also fit the translation to each instance's box (with the predicted and with the "
                             "ground-truth rotation), report its error and score the full 6-D poses")
    parser.add_argument("--depth", action="store_true",
                        help="also place each instance with its image's depth (depth/ and scene_camera.json's "
                             "depth_scale) as the runtime does, beside the box (implies --translation): translation "
                             "error, 6-D scores, the instances that fell back to the box and why, and the depth "
                             "step's ms per instance. The models need surface points (this version's export)")
    parser.add_argument("--refine", action="store_true",
                        help="with --depth: also refine rotation and translation against the observed points (ICP, "
                             "needs pip install ./runtime[depth]); scored as a row of its own. With --top-k K the "
                             "refinement starts from the code's K strongest poses")
    parser.add_argument("--threads", type=int, default=0, metavar="N",
                        help="onnxruntime intra-op threads of ONNX models (0: all cores, the default); 1 times the "
                             "depth step as on one core (idle worker threads spinning beside it slow it)")
    depth = parser.add_mutually_exclusive_group()
    depth.add_argument("--vsd", dest="vsd", action="store_const", const=True,
                       help="require VSD, e_VSD<0.3 and VSS (an error if the split has no depth images)")
    depth.add_argument("--no-vsd", dest="vsd", action="store_const", const=False,
                       help="skip the depth-based metrics (default: computed when the split has depth)")
    parser.add_argument("--max-instances", type=int, metavar="N", help="evaluate at most N instances per object")
    parser.add_argument("--min-visib-fract", type=float, default=BOP19_MIN_VISIB_FRACT,
                        help=f"leave out instances with less of the object visible (default, as BOP19: "
                             f"{BOP19_MIN_VISIB_FRACT})")
    parser.add_argument("--box-noise", metavar="PRESET",
                        help="crop each instance from a detector-like box instead of its ground-truth box: "
                             f"{', '.join(BOX_NOISE_PRESETS)} (typical IoU 1, 0.9, 0.75, 0.6); the report gains "
                             "MSSD by box IoU, the errors CSV a box_iou column")
    parser.add_argument("--box-noise-seed", type=int, default=0, metavar="N",
                        help="seed of the detector-like boxes (default 0; popcode-train detections --seed N writes "
                             "the same boxes)")
    parser.add_argument("--top-k", type=int, default=1, metavar="K",
                        help=f"also score the best of a population code's top K distinct hypotheses (MSSD; 1 to "
                             f"{MAX_TOP_K}, default 1: the estimate alone)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if args.refine and not args.depth:
        raise PopcodeError("--refine refines each pose against its image's depth: add --depth")
    if not 1 <= args.top_k <= MAX_TOP_K:
        raise PopcodeError(f"--top-k must lie in [1, {MAX_TOP_K}], got {args.top_k}")
    noise = None if args.box_noise is None else box_noise_preset(args.box_noise)
    check_threads(args.threads)
    if args.box_noise_seed < 0:
        raise PopcodeError(f"--box-noise-seed must be 0 or more, got {args.box_noise_seed}")
    for split_dir in args.splits:  # cheap checks first: folders, then every model with the options
        require_folder(split_dir, "split folder")
    require_folder(args.models_dir, "models folder")
    _check_out_folder(args.out)
    inputs = [*args.splits, args.models_dir, *args.models]
    refuse_inputs(args.out, "--out", inputs)
    methods = methods_from_paths(args.models, args.names, args.decoders, args.threads)
    depth_keys = [mode.key for mode in depth_modes(args.refine)] if args.depth else []
    for name in report_files([method.name for method in methods], args.bop19_csv, depth_keys):
        if args.out.is_dir():  # before any work: never an input, a link or FIFO, and existing only with --overwrite
            check_output_file(args.out / name, "--out", inputs, args.overwrite)
        elif len(name.encode()) > MAX_NAME_BYTES:
            raise PopcodeError(f"--out: the file name {name[:40]}... is {len(name.encode())} bytes; at most "
                               f"{MAX_NAME_BYTES}: give the method a shorter --name")
    with folder_lock(args.out, EVALUATE_LOCK, f"another popcode-train evaluate is writing {args.out} (it holds "
                                              f"{EVALUATE_LOCK}); wait for it to end, or give another --out"):
        split = read_eval_split(args.splits, args.models_dir, args.obj_ids, args.max_instances, args.min_visib_fract)
        if noise is not None:  # once, before any method: every method and the translation fit crop the same boxes
            split = with_detector_boxes(split, noise, args.box_noise_seed)
        results = evaluate_models(methods, split, vsd=args.vsd, obj_ids=args.obj_ids, translation=args.translation,
                                  top_k=args.top_k, depth=args.depth, refine=args.refine)
        written = write_report(results, args.out, bop19_csv=args.bop19_csv)
    print(report_markdown(results))
    for result in results:
        if result.matching is not None:
            print(_matching_line(result.name, len(result.split.instances), result.matching))
    print("wrote " + ", ".join(str(path) for path in written))
    return 0


def _matching_line(name: str, instances: int, matching: ResultsMatching) -> str:
    """What matching a results file to the split left over, so that a detector's misses and extras show."""
    return (f"{name}: {matching.without_estimate} of {instances} instances had no estimate (scored wrong); "
            f"estimates ignored: {matching.extra} beyond their image and object's instance count, "
            f"{matching.without_instance} of an image and object without an instance to score")


def _check_out_folder(out: Path) -> None:
    """``--out`` is a writable folder, or can be made one: nothing but folders on the way, the first it makes in
    a writable one (checked before any work)."""
    if os.path.lexists(out) and not out.is_dir():
        raise PopcodeError(f"--out {out} is not a folder (a file, link or FIFO); give a folder for the report")
    made = out  # the first folder on the way that does not exist yet, or --out itself
    while not os.path.lexists(made.parent) and made.parent != made.parent.parent:  # a dangling link stops the walk
        made = made.parent
    if not made.parent.is_dir():
        raise PopcodeError(f"--out {out}: {made.parent} is not a folder, so the report's folder cannot be made")
    check_writable_file(out / EVALUATE_LOCK if out.is_dir() else made, "--out")
