"""``popcode-train train``: train a model from a TOML config (one process or under torchrun)."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from popcode_runtime.base.files import refuse_inputs

from ..train.config import load_config
from ..train.loop import run_lock, train
from ..train.pretrained import resolve_start


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train", help="train a network on BOP data",
        description="Train per a TOML config; checkpoints and metrics.csv go to train.out_dir. "
                    "Run under 'torchrun --nproc_per_node=N' for several processes.")
    parser.add_argument("--config", help="TOML file with [data], [code], [network], [train] tables "
                                         "(omitted: the paper's defaults)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one setting, e.g. --set train.lr=1e-3 (repeatable; value in TOML syntax)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run in train.out_dir from its last checkpoint")
    parser.add_argument("--from-scratch", action="store_true",
                        help="start from random weights (same as --set train.init='\"none\"'), not from the "
                             "shipped pretrained start of the network (train.init 'auto', the default)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    config = load_config(args.config, [*args.overrides, *(['train.init="none"'] if args.from_scratch else [])])
    if not args.resume:  # a start that does not fit is refused before the data are read
        resolve_start(config.train.init, replace(config.network, input_size=config.data.crop_size))
    from ..train.training_data import build_training_data, read_training_split  # once the config is valid

    refuse_inputs(Path(config.train.out_dir), "train.out_dir",
                  [*config.data.splits, *filter(None, [config.data.models_dir])])
    split = read_training_split(config)  # the data checked before the run folder is made
    with run_lock(config.train.out_dir):  # before the crop cache, which lies in the run folder by default
        data = build_training_data(config, split=split)
        train(config, data.representation, data.train_set, data.val_set, resume=args.resume,
              val_instances=data.val_instances, locked=True)
    return 0
