"""``popcode-train pretrain``: a trunk trained on many generated parts, the start of other parts' models."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.base.output_lock import folder_lock

from ..data.generated_parts import MAX_PARTS
from ..demo.pretraining import PretrainSize, pretrain
from ..train.config import MAX_EPOCHS
from ..train.network import NetworkConfig
from ..train.pretrained import describe, read_start, shipped_path

LOCK = "pretrain.lock"  # in --out while a pretraining writes it


def register(subparsers: argparse._SubParsersAction) -> None:
    defaults = PretrainSize()
    parser = subparsers.add_parser(
        "pretrain", help="train a trunk on many generated parts: the start of every other model (train.init)",
        description="Generate CAD-like parts with their exact symmetries (n-fold, none, and look-alike parts that "
                    "are symmetric but for one small feature), render them singly and in bins, train one "
                    "population-code model of the demo's network on all of them, and save its trunk as a "
                    "pretrained start (--out/pretrained-start.pt, with a card of what it saw). train and demo start "
                    "from the shipped start of their network (--ship puts this one there) unless given "
                    "--from-scratch. Rerun the same command to resume an interrupted run.")
    parser.add_argument("--out", type=Path, default=Path("runs/pretrain"), help="run folder (default: %(default)s)")
    parser.add_argument("--parts", type=int, default=defaults.parts, help="generated parts (default %(default)s)")
    parser.add_argument("--images", type=int, default=defaults.images_per_part,
                        help="single-part training images per part (default %(default)s)")
    parser.add_argument("--scenes", type=int, default=defaults.scenes,
                        help="bin scenes of the generated parts (default %(default)s; 0: none)")
    parser.add_argument("--minutes", type=float, default=defaults.minutes,
                        help="fit the epochs so training takes about M minutes (default %(default)s)")
    parser.add_argument("--epochs", type=int, help="train this many epochs instead of fitting them to --minutes")
    parser.add_argument("--seed", type=int, default=defaults.seed, help="draws the parts (default %(default)s)")
    parser.add_argument("--ship", action="store_true",
                        help="copy the start into the repository's models/ as the shipped start of its network")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    for option, value, lowest, most in (("--parts", args.parts, 1, MAX_PARTS), ("--images", args.images, 1, 100_000),
                                        ("--scenes", args.scenes, 0, 100_000), ("--minutes", args.minutes, 1e-3, 1e5),
                                        ("--epochs", args.epochs, 2, MAX_EPOCHS), ("--seed", args.seed, 0, 2**31)):
        if value is not None and not (lowest <= value <= most and math.isfinite(value)):
            raise PopcodeError(f"{option} must lie in [{lowest:g}, {most:,}], got {value}")
    size = PretrainSize(parts=args.parts, images_per_part=args.images, scenes=args.scenes, minutes=args.minutes,
                        epochs=args.epochs, seed=args.seed)
    if args.out.is_file():
        raise PopcodeError(f"--out {args.out} is a file; a pretraining writes a folder")
    with folder_lock(args.out, LOCK, f"another popcode-train pretrain is writing {args.out} (it holds {LOCK}); "
                                     "wait for it to end, or write into another --out"):
        path = pretrain(size, args.out)
    start = read_start(path)
    print(f"pretrained start written to {path} ({describe(start)})")
    if args.ship:
        shipped = shipped_path(NetworkConfig(**{k: tuple(v) if isinstance(v, list) else v
                                                for k, v in start.network.items()}))
        write_bytes_atomic(shipped, path.read_bytes())
        print(f"shipped as {shipped}: train and demo of this network now start from it")
    return 0
