"""``popcode-train train-detector``: a detector of the parts in BOP scene splits, trained and exported."""

from __future__ import annotations

import argparse
from pathlib import Path

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import refuse_inputs, require_folder

from ..detection.config import DetectorConfig
from ..train.config import parse_override
from ..train.pretrained import NONE

DETECTOR_FILE = "detector.onnx"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train-detector", help="train a detector of the parts on BOP scene splits and export it",
        description="Train torchvision's FCOS on the images and boxes of BOP scene splits (what popcode-train "
                    "render --scenes writes), from the shipped detector start of its network shape where there is "
                    "one (detector.init; --from-scratch: random weights), holding out a share of the images for a "
                    "validation "
                    f"loss; checkpoint after each epoch (rerun the same command to resume) and write "
                    f"OUT/{DETECTOR_FILE} for popcode detect, popcode run --detector and popcode predict --detector.")
    parser.add_argument("--split", action="append", required=True, type=Path, metavar="DIR",
                        help="BOP scene split to learn from (repeatable)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="run folder: checkpoint, metrics, "
                                                                                 "detector.onnx")
    parser.add_argument("--obj-ids", type=int, nargs="+", metavar="ID",
                        help="objects to detect (default: every object annotated in the splits)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="detector.KEY=VALUE",
                        help="override a setting, e.g. --set detector.epochs=60 (repeatable; settings: "
                             f"{', '.join(DetectorConfig().to_dict())})")
    parser.add_argument("--minutes", type=float, metavar="M",
                        help="fit the epochs to about M minutes of training from the first epoch's time "
                             "(at most detector.epochs)")
    parser.add_argument("--from-scratch", action="store_true",
                        help="random first weights (detector.init 'none') instead of the shipped detector start")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.set_defaults(handler=run)


def detector_config(overrides: list[str], from_scratch: bool = False) -> DetectorConfig:
    """The default config with ``--set detector.KEY=VALUE`` overrides (and ``--from-scratch``), checked."""
    values = {}
    for text in overrides:
        section, key, value = parse_override(text)
        if section != "detector":
            raise PopcodeError(f"train-detector settings are detector.KEY=VALUE, got {text!r}")
        values[key] = value
    if from_scratch:
        values["init"] = NONE
    return DetectorConfig().with_overrides(values)


def run(args: argparse.Namespace) -> int:
    config = detector_config(args.overrides, args.from_scratch)
    if args.minutes is not None and not 0 < args.minutes <= 100_000:
        raise PopcodeError(f"--minutes must lie in (0, 100000], got {args.minutes}")
    for split in args.split:
        require_folder(split, "--split")
    refuse_inputs(args.out, "--out", args.split)
    from ..detection.export import export_detector
    from ..detection.frames import split_objects
    from ..detection.loop import train_detector

    held = split_objects(args.split)
    absent = sorted(set(args.obj_ids or ()) - set(held))
    if absent:
        raise PopcodeError(f"--obj-ids: the splits hold no instance of object{'s' if len(absent) > 1 else ''} "
                           f"{', '.join(map(str, absent))}; they hold objects {', '.join(map(str, held))}")
    obj_ids = args.obj_ids or held
    run = train_detector(args.split, obj_ids, args.out, config,
                         seconds=None if args.minutes is None else 60.0 * args.minutes, progress=not args.quiet)
    path = export_detector(run.checkpoint, args.out / DETECTOR_FILE)
    print(f"wrote {path}: objects {list(run.obj_ids)}, {run.config.epochs} epochs, input "
          f"{run.config.input_width}x{run.config.input_height}, first weights from {run.start}")
    return 0
