"""``popcode-train render``: single objects (``--images``) or cluttered scenes (``--scenes``) as a BOP split."""

from __future__ import annotations

import argparse
import re
from contextlib import AbstractContextManager
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import refuse_inputs
from popcode_runtime.base.output_lock import folder_lock

from ..data.bop import RENDER_MARKER
from ..data.objects import BUILTIN_PARTS, write_builtin_models
from ..data.render import BUILTIN_MODELS_FOLDER, RenderSettings, parse_shard, render_split
from ..data.scene_content import SceneSettings
from ..data.scene_render import render_scene_split
from ..data.sensor import SENSOR_PRESETS

SINGLE_OBJECT_SIZE = (128, 128)
SCENE_SIZE = (720, 540)
# SceneSettings fields; None: its default
SCENE_OPTIONS = ("parts", "distractors", "bin", "bin_size_mm", "sensor", "empty_share")
SHARD_LOCK = ".render-{index}-of-{count}.lock"  # held in the split folder while a render writes that shard
SHARD_LOCK_NAME = re.compile(r"\.render-\d+-of-\d+\.lock")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "render", help="render single objects or cluttered scenes of them into a BOP split",
        description="Render objects at uniform random rotations with random lights and shade into a BOP-format "
                    "split (--images: one object per image), or cluttered scenes of several parts and distractors "
                    "dropped into a bin and seen from above (--scenes), with masks, visibility and depth as the "
                    "BOP toolkit writes them. Rerun the same command to complete an interrupted render; shards "
                    "(--shard i/n) rendered into one folder, or copied together and rerun, form one split. A second "
                    "render of the same shard into one folder is refused while the first runs.")
    parser.add_argument("--objects", required=True,
                        help="'builtin' (written to OUT/models) or a BOP models folder with models_info.json")
    parser.add_argument("--out", required=True, type=Path, help="split folder to write")
    mode = parser.add_mutually_exclusive_group(required=True)
    mode.add_argument("--images", type=int, help="single objects: images per object")
    mode.add_argument("--scenes", type=int, help="cluttered scenes: number of images, each a new scene")
    parser.add_argument("--size", nargs=2, type=int, metavar=("W", "H"),
                        help=f"image size px (default {SINGLE_OBJECT_SIZE} with --images, {SCENE_SIZE} with --scenes)")
    parser.add_argument("--shard", default="0/1", help="render part i of n (default 0/1: everything)")
    parser.add_argument("--seed", type=int, default=0,
                        help="the same seed renders the same images (default 0; another one for a test split)")
    parser.add_argument("--obj-ids", nargs="+", type=int, help="objects to render (default: all)")
    colour = parser.add_mutually_exclusive_group()
    colour.add_argument("--gray", dest="gray", action="store_true", default=True, help="grey images (default)")
    colour.add_argument("--rgb", dest="gray", action="store_false", help="colour images")
    parser.add_argument("--random-position", action="store_true", help="place objects anywhere in the image")
    parser.add_argument("--fixed-distance", action="store_true", help="keep every object at one distance")
    scenes = parser.add_argument_group("scenes (with --scenes)")
    scenes.add_argument("--parts", nargs=2, type=int, metavar=("MIN", "MAX"),
                        help="target parts per image, drawn from the models with repeats (default 4 10)")
    scenes.add_argument("--distractors", nargs=2, type=int, metavar=("MIN", "MAX"),
                        help="boxes, cylinders, capsules and spheres per image that are not targets (default 0 3)")
    scenes.add_argument("--no-bin", dest="bin", action="store_false", default=None,
                        help="parts on an open table, no bin walls")
    scenes.add_argument("--bin-size-mm", type=float,
                        help="side of the bin (default: from the largest part and the most objects per image)")
    scenes.add_argument("--sensor", choices=sorted(SENSOR_PRESETS),
                        help="camera effects (noise, blur, exposure, gamma, JPEG) and a depth camera's depth "
                             "(noise, holes, quantisation) resembling a camera kind (default none: exact depth; "
                             "see the README)")
    scenes.add_argument("--empty-share", type=float, metavar="P",
                        help="share of the images without parts, half of them also without distractors (their "
                             "ground-truth lists are empty): negatives for train-detector (default 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(handler=run)


def _check_mode_options(args: argparse.Namespace) -> None:
    """Options of the other mode are refused, not ignored."""
    if args.scenes is None:
        scene_options = [f"--{name.replace('_', '-')}" for name in SCENE_OPTIONS if getattr(args, name) is not None]
        if scene_options:
            raise PopcodeError(f"only with --scenes, not with --images: {', '.join(scene_options)}")
    elif args.random_position or args.fixed_distance:
        raise PopcodeError("only with --images, not with --scenes: --random-position, --fixed-distance")


def run(args: argparse.Namespace) -> int:
    _check_mode_options(args)
    if args.out.is_file():
        raise PopcodeError(f"--out {args.out} is a file; a split is written into a folder")
    shard = parse_shard(args.shard)  # every option checked before anything is written
    settings = _scene_settings(args) if args.scenes is not None else _image_settings(args)
    if args.out.is_dir() and not (args.out / RENDER_MARKER).is_file() and any(
            entry.name != BUILTIN_MODELS_FOLDER and not SHARD_LOCK_NAME.fullmatch(entry.name)
            for entry in args.out.iterdir()):
        raise PopcodeError(f"--out {args.out} holds files but no {RENDER_MARKER}: not a split this command made "
                           "(or one whose settings are lost); render into an empty or new folder")
    if args.objects == "builtin":
        unknown = sorted(set(args.obj_ids or ()) - {part.obj_id for part in BUILTIN_PARTS})
        if unknown:
            raise PopcodeError(f"--obj-ids {unknown}: the built-in parts are objects "
                               f"{', '.join(str(part.obj_id) for part in BUILTIN_PARTS)}")
        if (args.out / RENDER_MARKER).is_file() and not (args.out / BUILTIN_MODELS_FOLDER).is_dir():
            raise PopcodeError(f"--out {args.out} was rendered from other models (it has no "
                               f"{BUILTIN_MODELS_FOLDER}/ folder); render the built-in parts into another folder")
    elif not Path(args.objects).is_dir():
        raise PopcodeError(f"--objects: no such models folder {args.objects} (or use 'builtin')")
    else:
        refuse_inputs(args.out, "--out", [args.objects])
    with _shard_lock(args.out, shard):
        if args.objects == "builtin":
            models_dir = write_builtin_models(args.out / BUILTIN_MODELS_FOLDER)
        else:
            models_dir = Path(args.objects)
        if isinstance(settings, SceneSettings):
            return _run_scenes(args, models_dir, settings, shard)
        render_split(models_dir, args.out, settings, obj_ids=args.obj_ids, shard=shard, progress=not args.quiet)
    print(f"split written to {args.out} (models: {models_dir})")
    return 0


def _shard_lock(out: Path, shard: tuple[int, int]) -> AbstractContextManager[None]:
    """One writer per shard, not per folder: the shards of a split render side by side into one folder."""
    name = SHARD_LOCK.format(index=shard[0], count=shard[1])
    return folder_lock(out, name, f"another popcode-train render is writing shard {shard[0]}/{shard[1]} of {out} "
                                  f"(it holds {name}); wait for it to end, or render another --shard or into "
                                  "another --out")


def _image_settings(args: argparse.Namespace) -> RenderSettings:
    width, height = args.size or SINGLE_OBJECT_SIZE
    return RenderSettings(args.images, width=width, height=height, seed=args.seed, gray=args.gray,
                          random_position=args.random_position, random_distance=not args.fixed_distance)


def _scene_settings(args: argparse.Namespace) -> SceneSettings:
    width, height = args.size or SCENE_SIZE
    given = {name: tuple(value) if isinstance(value, list) else value
             for name in SCENE_OPTIONS if (value := getattr(args, name)) is not None}
    return SceneSettings(args.scenes, width=width, height=height, seed=args.seed, gray=args.gray, **given)


def _run_scenes(args: argparse.Namespace, models_dir: Path, settings: SceneSettings, shard: tuple[int, int]) -> int:
    stats = render_scene_split(models_dir, args.out, settings, obj_ids=args.obj_ids, shard=shard,
                               progress=not args.quiet)
    if stats.images:
        print(f"rendered {stats.images} scenes with {stats.instances} target instances in {stats.seconds:.1f} s: "
              f"{stats.images / stats.seconds:.2f} scenes/s, {stats.instances / stats.seconds:.1f} instances/s")
    print(f"split written to {args.out} (models: {models_dir})")
    return 0
