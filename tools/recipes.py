"""The networks and the shipped recipe that bench and experiments train: ``bench.training`` times
:data:`NETWORKS`; ``experiments.shipped_models`` reads its command line with :func:`shipped_arguments` and trains
:func:`shipped_size`, the medium demo's recipe with the changes it names (one of the networks, say)."""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from popcode_trainer.demo.report import POPCODE
from popcode_trainer.demo.sizes import DEMO_SIZES, DemoSize
from popcode_trainer.demo.steps import SMALL_NETWORK, PipelineSize
from popcode_trainer.kit.budget import WIDE_NETWORK
from popcode_trainer.train.fast_path import COMPILE_CHOICES
from popcode_trainer.train.network import NetworkConfig

# The MLP of the width runs below (network-width.md), measured before the quick recipe's became 512 / 256 / 256.
WIDTH_RUNS_HIDDEN = (256, 128, 128)
NETWORKS = {
    "tiny": NetworkConfig(conv_channels=(4, 4, 4), squeeze_channels=2, hidden=(16, 16, 16)),  # smoke tests only
    "small": SMALL_NETWORK,  # the quick recipe's network
    "small-paper-trunk": replace(SMALL_NETWORK, trunk="paper", conv_channels=(16, 32, 32),  # before the quick recipe
                                 hidden=WIDTH_RUNS_HIDDEN),
    # The quick recipe's trunk 2x to 6x as wide, with the MLP they were measured with: the capacity question of
    # the bin (bench/results/network-width.md). Past 3x the curve flattens.
    "small-x2": replace(SMALL_NETWORK, conv_channels=(32, 64, 128), squeeze_channels=16, hidden=WIDTH_RUNS_HIDDEN),
    "small-x3": WIDE_NETWORK,  # the shipped 3-6 model's trunk, which the kit trains from its third anchor on
    "small-x4": replace(SMALL_NETWORK, conv_channels=(64, 128, 256), squeeze_channels=32, hidden=WIDTH_RUNS_HIDDEN),
    "small-x6": replace(SMALL_NETWORK, conv_channels=(96, 192, 384), squeeze_channels=48, hidden=WIDTH_RUNS_HIDDEN),
    # 3x with a 512-wide first hidden layer (scored as the shipped small-x3 at its budget: head-width.md); the last
    # layer stays 128 wide, so that the nbits8-fp16 export keeps under the repository's 8 MB a model.
    "small-x3-h512": replace(SMALL_NETWORK, conv_channels=(48, 96, 192), squeeze_channels=24, hidden=(512, 256, 128)),
    "paper": NetworkConfig(),
}
SHIPPED_SIZE = "medium"  # the demo size whose recipe the shipped models are trained with


def shipped_arguments(argv: Sequence[str] | None,
                      description: str = "") -> tuple[argparse.Namespace, argparse.ArgumentParser]:
    """The command line of ``experiments.shipped_models`` and its parser: a value the recipe cannot take ends it
    with argparse's one line and status 2, before anything is rendered."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--minutes", type=float, default=8.0, help="budget of the whole run (default 8)")
    parser.add_argument("--out", type=Path, default=Path("runs/shipped"))
    parser.add_argument("--copy-to", type=Path, help="copy each model's exports here once it is exported")
    parser.add_argument("--images", type=int, help="training images per part instead of the medium size's")
    parser.add_argument("--scenes", type=int, help="training scenes instead of the medium size's")
    parser.add_argument("--test-images", type=int, metavar="N",
                        help="test images per part instead of the medium size's (rendered beside the training data, "
                             "never trained on: few for a check of the script)")
    parser.add_argument("--group", nargs="+", type=int, metavar="OBJ_ID",
                        help="train only the model of the object group holding these parts (default: every group)")
    parser.add_argument("--compile", choices=COMPILE_CHOICES, default="auto", help="train.compile (default auto)")
    parser.add_argument("--box-noise-p", type=float, metavar="P",
                        help="share of the crops cut from detector-like boxes instead of the medium size's")
    parser.add_argument("--scene-share", type=float, metavar="S",
                        help="share of an epoch's crops cut from the training scenes instead of the medium size's")
    parser.add_argument("--network", choices=list(NETWORKS),
                        help="the network to train instead of the medium size's (tools.recipes.NETWORKS)")
    parser.add_argument("--traced-images", type=int, default=0, metavar="N",
                        help="single-part training images a part path traced (popcode-train path-trace; default 0)")
    parser.add_argument("--traced-share", type=float, default=0.0, metavar="S",
                        help="share of an epoch's crops from the path-traced images (with --traced-images)")
    parser.add_argument("--init", metavar="START",
                        help="train.init: the first weights, e.g. a start experiments.shipped_start wrote from a "
                             "shipped model, to fine-tune it (default the medium size's)")
    parser.add_argument("--lr", type=float,
                        help="train.lr instead of the medium size's (a fine-tune takes a lower one)")
    parser.add_argument("--render-only", action="store_true", help="render the data into --out and stop")
    args = parser.parse_args(argv)
    if args.lr is not None and not 0.0 < args.lr < 1.0:  # NaN too
        parser.error(f"--lr must lie in (0, 1), not {args.lr}")
    if not args.minutes > 0:
        parser.error(f"--minutes must be positive, not {args.minutes}")
    if args.box_noise_p is not None and not 0.0 < args.box_noise_p <= 1.0:  # NaN too
        parser.error(f"--box-noise-p must lie in (0, 1], not {args.box_noise_p}")
    if args.scene_share is not None and not 0.0 < args.scene_share < 1.0:
        parser.error(f"--scene-share must lie in (0, 1), not {args.scene_share}")
    if args.test_images is not None and args.test_images < 1:
        parser.error(f"--test-images must be at least 1, not {args.test_images}")
    return args, parser


def shipped_size(args: argparse.Namespace) -> tuple[DemoSize, PipelineSize]:
    """The medium demo fitted to ``args.minutes``, and the run it makes: the population code alone, with the
    data, compile, network, box-noise, scene-share, first-weights and rate choices of ``args`` (``None``: the medium
    size's)."""
    demo = replace(DEMO_SIZES[SHIPPED_SIZE], minutes=args.minutes)
    config = demo.pipeline.config
    config = replace(config, train=replace(config.train, compile=args.compile, init=args.init or config.train.init,
                                           lr=args.lr or config.train.lr))
    if args.network is not None:
        config = replace(config, network=NETWORKS[args.network])  # output_dim follows each model's code
    if args.box_noise_p is not None:
        config = replace(config, data=replace(config.data, box_noise_p=args.box_noise_p))
    test_images = args.test_images or demo.pipeline.test_images_per_object
    size = replace(demo.pipeline, representations=(POPCODE,), config=config,
                   train_images_per_object=args.images or demo.pipeline.train_images_per_object,
                   train_scenes=args.scenes or demo.pipeline.train_scenes,
                   test_images_per_object=test_images,  # the demo path traces the first of them; these runs never
                   path_traced_images=min(demo.pipeline.path_traced_images, test_images),
                   scene_share=demo.pipeline.scene_share if args.scene_share is None else args.scene_share,
                   traced_train_images=args.traced_images, traced_share=args.traced_share)
    return demo, size
