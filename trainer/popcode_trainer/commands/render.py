"""``popcode-train render``: render objects into a BOP-format training split."""

from __future__ import annotations

import argparse
from pathlib import Path

from popcode_runtime.errors import PopcodeError

from ..data.objects import write_builtin_models
from ..data.render import BUILTIN_MODELS_FOLDER, RenderSettings, parse_shard, render_split


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "render", help="render objects at uniformly random rotations into a BOP split",
        description="Render objects at uniform random rotations with random lights and shade into a BOP-format "
                    "split. Rerun the same command to complete an interrupted render; shards (--shard i/n) "
                    "rendered into one folder, or copied together and rerun, form one split.")
    parser.add_argument("--objects", required=True,
                        help="'builtin' (written to OUT/models) or a BOP models folder with models_info.json")
    parser.add_argument("--out", required=True, type=Path, help="split folder to write")
    parser.add_argument("--images", required=True, type=int, help="images per object")
    parser.add_argument("--size", nargs=2, type=int, default=(128, 128), metavar=("W", "H"), help="image size px")
    parser.add_argument("--shard", default="0/1", help="render part i of n (default 0/1: everything)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--obj-ids", nargs="+", type=int, help="objects to render (default: all)")
    colour = parser.add_mutually_exclusive_group()
    colour.add_argument("--gray", dest="gray", action="store_true", default=True, help="grey images (default)")
    colour.add_argument("--rgb", dest="gray", action="store_false", help="colour images")
    parser.add_argument("--random-position", action="store_true", help="place objects anywhere in the image")
    parser.add_argument("--fixed-distance", action="store_true", help="keep every object at one distance")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if args.out.is_file():
        raise PopcodeError(f"--out {args.out} is a file; a split is written into a folder")
    if args.objects == "builtin":
        models_dir = write_builtin_models(args.out / BUILTIN_MODELS_FOLDER)
    else:
        models_dir = Path(args.objects)
        if not models_dir.is_dir():
            raise PopcodeError(f"--objects: no such models folder {models_dir} (or use 'builtin')")
    settings = RenderSettings(args.images, width=args.size[0], height=args.size[1], seed=args.seed, gray=args.gray,
                              random_position=args.random_position, random_distance=not args.fixed_distance)
    render_split(models_dir, args.out, settings, obj_ids=args.obj_ids, shard=parse_shard(args.shard),
                 progress=not args.quiet)
    print(f"split written to {args.out} (models: {models_dir})")
    return 0
