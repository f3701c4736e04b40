"""``popcode-train path-trace``: a rendered split again, path traced with physically based materials and lights."""

from __future__ import annotations

import argparse
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import refuse_inputs
from popcode_runtime.base.output_lock import folder_lock

from ..data.path_trace import INSTALL_HINT, MAX_SAMPLES, PathTraceSettings
from ..data.path_traced_split import path_trace_split

LOCK = "path-trace.lock"  # in --out while a path trace writes it


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "path-trace", help="re-render a rendered split with a physically based path tracer (Mitsuba 3)",
        description="Render a split that popcode-train render made again with Mitsuba 3's path tracer: the same "
                    "parts, poses, camera, bin and sensor effects, but rough aluminium, steel and plastic parts, area "
                    "lights, interreflections and render noise. Depth, masks and ground truth are copied, so scores "
                    "on the two splits pair up instance by instance: the gap between them is what the rasteriser's "
                    f"look costs. Needs the optional extra: {INSTALL_HINT}. Rerun the same command to complete an "
                    "interrupted run.")
    parser.add_argument("--split", required=True, type=Path, help="a split made by popcode-train render")
    parser.add_argument("--out", required=True, type=Path, help="split folder to write")
    parser.add_argument("--models-dir", type=Path,
                        help="the models the split was rendered from (default: SPLIT/models, where the built-in "
                             "parts are written)")
    parser.add_argument("--samples", type=int, default=PathTraceSettings.samples,
                        help=f"samples per pixel, 1 to {MAX_SAMPLES} (default %(default)s: some grain, as a camera's)")
    parser.add_argument("--max-depth", type=int, default=PathTraceSettings.max_depth,
                        help="longest light path in segments (default %(default)s)")
    parser.add_argument("--seed", type=int, default=PathTraceSettings.seed,
                        help="draws the materials and lights (default %(default)s)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    settings = PathTraceSettings(samples=args.samples, max_depth=args.max_depth, seed=args.seed)
    if not args.split.is_dir():
        raise PopcodeError(f"--split {args.split}: no such folder")
    if args.out.is_file():
        raise PopcodeError(f"--out {args.out} is a file; a split is written into a folder")
    refuse_inputs(args.out, "--out", [args.split, *filter(None, [args.models_dir])])
    with folder_lock(args.out, LOCK, f"another popcode-train path-trace is writing {args.out} (it holds {LOCK}); "
                                     "wait for it to end, or write into another --out"):
        stats = path_trace_split(args.split, args.out, settings, models_dir=args.models_dir, progress=not args.quiet)
    if stats.images:
        print(f"path traced {stats.images} images in {stats.seconds:.1f} s ({stats.seconds / stats.images:.2f} s an "
              "image)")
    print(f"split written to {args.out}")
    return 0
