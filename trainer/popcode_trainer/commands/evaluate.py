"""``popcode-train evaluate``: models + a BOP split -> per-instance errors and the paper's tables."""

from __future__ import annotations

import argparse
from pathlib import Path

from popcode_runtime.bop_split import BOP19_MIN_VISIB_FRACT
from popcode_runtime.decoding import DECODERS
from popcode_runtime.errors import PopcodeError
from popcode_runtime.files import require_folder

from ..eval.pipeline.evaluate import evaluate_models
from ..eval.pipeline.models import methods_from_paths
from ..eval.pipeline.split import read_eval_split
from ..eval.reporting.report import report_markdown, write_report


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "evaluate", help="score models on a BOP split with the BOP rotation metrics",
        description="Rotation from each model, translation from the ground truth (the paper's protocol). Writes "
                    "per-instance errors (CSV), the per-object and with/without-ambiguity tables (markdown, JSON) "
                    "and, if asked, BOP19 results files. Models given the same --name form one method (e.g. one "
                    "model per object group). With --translation, full 6-D poses too: the translation fitted to "
                    "each box as the runtime does it.")
    parser.add_argument("models", nargs="+", type=Path, metavar="MODEL",
                        help="a training checkpoint (.pt, run with torch), an ONNX model (run with the runtime) or a "
                             "BOP19 results file (.csv, e.g. from popcode run --gt-boxes; scored rotation-only)")
    parser.add_argument("--split", dest="splits", action="append", required=True, type=Path, metavar="DIR",
                        help="BOP split folder with scene folders (repeatable)")
    parser.add_argument("--models-dir", type=Path, required=True,
                        help="folder with the object meshes obj_XXXXXX.ply and models_info.json")
    parser.add_argument("--name", dest="names", action="append", default=[], metavar="NAME",
                        help="table row of each MODEL, in order (repeatable; default: the file name)")
    parser.add_argument("--obj-ids", nargs="+", type=int, metavar="ID", help="evaluate only these objects")
    parser.add_argument("--decoder", choices=DECODERS, default="argmax",
                        help="how a population code becomes a rotation (default: argmax, the paper's)")
    parser.add_argument("--out", type=Path, default=Path("eval"), help="output folder (default: ./eval)")
    parser.add_argument("--bop19-csv", action="store_true", help="also write a BOP19 results CSV per method")
    parser.add_argument("--translation", action="store_true",
                        help="also fit the translation to each instance's box (with the predicted and with the "
                             "ground-truth rotation), report its error and score the full 6-D poses")
    depth = parser.add_mutually_exclusive_group()
    depth.add_argument("--vsd", dest="vsd", action="store_const", const=True,
                       help="require VSD, e_VSD<0.3 and VSS (an error if the split has no depth images)")
    depth.add_argument("--no-vsd", dest="vsd", action="store_const", const=False,
                       help="skip the depth-based metrics (default: computed when the split has depth)")
    parser.add_argument("--max-instances", type=int, metavar="N", help="evaluate at most N instances per object")
    parser.add_argument("--min-visib-fract", type=float, default=BOP19_MIN_VISIB_FRACT,
                        help=f"leave out instances with less of the object visible (default, as BOP19: "
                             f"{BOP19_MIN_VISIB_FRACT})")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    for split_dir in args.splits:  # cheap checks first: folders, then every model with the options
        require_folder(split_dir, "split folder")
    require_folder(args.models_dir, "models folder")
    if args.out.exists() and not args.out.is_dir():
        raise PopcodeError(f"--out {args.out} is a file; give a folder for the report")
    methods = methods_from_paths(args.models, args.names, args.decoder)
    split = read_eval_split(args.splits, args.models_dir, args.obj_ids, args.max_instances, args.min_visib_fract)
    results = evaluate_models(methods, split, vsd=args.vsd, obj_ids=args.obj_ids, translation=args.translation)
    written = write_report(results, args.out, bop19_csv=args.bop19_csv)
    print(report_markdown(results))
    print("wrote " + ", ".join(str(path) for path in written))
    return 0
