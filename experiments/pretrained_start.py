"""Pretrained start against random weights on parts no choice was tuned on: MSSD clean and in a bin against epochs,
and the look-alike part's right-pose share.

    python -m experiments.pretrained_start --start runs/pretrain/pretrained-start.pt [--epochs 3 6 12]
        [--parts validation|builtin] [--images 2000] [--scenes 150] [--representations population_code]
        [--arms scratch pretrained] [--work runs/pretrained_start] [--name pretrained-start]

Of the ``--parts`` (the validation parts of ``tools.own_parts``, or the built-in ones), the largest group that the
demo trains as one model on the quick size's 642 x 36 grid (validation: the flange, bracket, look-alike flange and
rod, not the 12-fold gear, which gets a finer grid, nor the shaft's axis-only code; built-in: parts 3-6) is
rendered as the quick demo renders a user's parts (``--images`` single-part images a part, seed 0, and
``--scenes`` bin scenes, seed 3000) and scored on a clean validation split (seed 5000, 40 images a part) and a bin
one (seed 4000, 40 scenes). Each arm trains the
quick demo's recipe (``small_config``: 642 x 36 code, batch 32, anneal, a quarter of the crops from the scenes) for
each of ``--epochs``, a run per budget (the anneal depends on the run's length): ``scratch`` from random weights,
``pretrained`` from ``--start``, ``pretrained-slow-trunk`` from it with the start's weights at 0.3 of the rate.
``--work`` keeps splits and runs: a rerun resumes. Results: ``bench/results/<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.files import read_json, write_json_atomic
from popcode_runtime.model.metadata import Representation
from popcode_trainer.data.near_symmetry import LookAlikeWarning
from popcode_trainer.data.objects import BUILTIN_PARTS
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.demo.parts import Parts, load_parts
from popcode_trainer.demo.run import prepare_parts
from popcode_trainer.demo.sizes import SCENE_SHARE
from popcode_trainer.demo.steps import TRAIN_SCENES_SEED_OFFSET, small_config
from popcode_trainer.eval.pipeline.evaluate import MethodResult
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.look_alike_share import look_alike_shares
from popcode_trainer.train.config import CodeConfig
from popcode_trainer.train.pretrained import NONE, describe, read_start
from popcode_trainer.train.training_data import build_training_data
from tools.command import run_command
from tools.experiment import (
    CLEAN_VALIDATION_SEED,
    CLUTTERED_VALIDATION_SEED,
    TRAIN_SEED,
    score_last_checkpoint,
    train_run,
    training_config,
    training_so_far,
)
from tools.own_parts import VALIDATION_PARTS, write_models
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

VALIDATION_IMAGES, VALIDATION_SCENES = 40, 40
QUICK_CODE = small_config(1, 642, 36).code  # the quick demo's grid; a group the demo moves to a finer one is left out
# arm -> whether it takes the start, and the rate of the start's weights as a share of the recipe's (init_lr_scale)
ARMS = {"scratch": (False, 1.0), "pretrained": (True, 1.0), "pretrained-slow-trunk": (True, 0.3)}


PART_SETS = {"validation": VALIDATION_PARTS, "builtin": BUILTIN_PARTS}


def _group(part_set: str, work: Path) -> tuple[list[Any], CodeConfig]:
    """The largest group of ``part_set`` that the demo trains on the quick size's own grid, and its code."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LookAlikeWarning)
        _, codes = prepare_parts(write_models(PART_SETS[part_set], work / "all_parts"), QUICK_CODE)
    on_grid = [g for g in codes if (g.code.n_axes, g.code.n_angles) == (QUICK_CODE.n_axes, QUICK_CODE.n_angles)]
    group = max(on_grid, key=lambda g: len(g.obj_ids))
    return [part for part in PART_SETS[part_set] if part.obj_id in group.obj_ids], group.code


def render(work: Path, part_set: str, images: int, scenes: int) -> tuple[Parts, CodeConfig, dict[str, Path]]:
    """The largest group of ``part_set`` on the quick grid (as the demo groups and codes them), its code, and its
    training and validation splits."""
    chosen, code = _group(part_set, work)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LookAlikeWarning)  # the chamfered flange is the look-alike part, on purpose
        parts = load_parts(write_models(chosen, work / "parts"))
        splits = {"train": parts.render_split(work / "train", images, TRAIN_SEED, True),
                  "train_scenes": parts.render_scenes(work / "train_scenes", scenes,
                                                      TRAIN_SEED + TRAIN_SCENES_SEED_OFFSET, True),
                  "clean": parts.render_split(work / "val_clean", VALIDATION_IMAGES, CLEAN_VALIDATION_SEED, True),
                  "bin": parts.render_scenes(work / "val_bin", VALIDATION_SCENES, CLUTTERED_VALIDATION_SEED, True)}
    return parts, code, splits


def _shares(result: MethodResult) -> dict[str, Any]:
    R_true = np.stack([instance.R_m2c for instance in result.split.instances])
    shares = look_alike_shares(result.R_est, R_true, result.errors.obj_id, result.split.models_info,
                               result.look_alikes)
    return {str(s.obj_id): {"poses": s.poses, "found_shape": s.found_shape, "right_share": s.right_share}
            for s in shares}


def point(work: Path, parts: Parts, code: CodeConfig, splits: dict[str, Path], arm: str, start: Path, epochs: int,
          representation: str) -> dict[str, Any]:
    """One arm trained for ``epochs`` (resumed) and scored; kept in ``work/points`` once done."""
    name = f"{arm}_{representation}_{epochs}"
    done = work / "points" / f"{name}.json"
    if done.is_file():
        return read_json(done)
    run_dir = work / "runs" / name
    takes_start, lr_scale = ARMS[arm]
    base = small_config(epochs, 642, 36, init=str(start) if takes_start else NONE, init_lr_scale=lr_scale)
    base = replace(base, code=code)
    base = replace(base, train=replace(base.train, representation=representation,
                                       loss=base.train.loss if representation == Representation.POPULATION_CODE
                                       else "mse"))
    config = training_config(base, run_dir, epochs, splits=(str(splits["train"]), str(splits["train_scenes"])),
                             split_weights=(1.0 - SCENE_SHARE, SCENE_SHARE), obj_ids=tuple(parts.obj_ids),
                             models_dir=str(splits["train"] / BUILTIN_MODELS_FOLDER),
                             cache_dir=str(work / "crop_cache"))
    train_run(config, build_training_data(config))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LookAlikeWarning)
        clean = score_last_checkpoint(run_dir, representation, splits["clean"], parts.obj_ids)
        in_bin = score_last_checkpoint(run_dir, representation, splits["bin"], parts.obj_ids)
    result = {"arm": arm, "representation": representation, "epochs": epochs, **training_so_far(run_dir),
              "clean_mssd": clean.groups["All objects"]["MSSD"], "bin_mssd": in_bin.groups["All objects"]["MSSD"],
              "clean_per_part": {str(k): v["MSSD"] for k, v in sorted(clean.per_object.items())},
              "bin_per_part": {str(k): v["MSSD"] for k, v in sorted(in_bin.per_object.items())},
              "look_alike_clean": _shares(clean), "look_alike_bin": _shares(in_bin)}
    done.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(done, result)
    return result


def to_markdown(points: Sequence[dict[str, Any]], start_text: str, args: argparse.Namespace) -> str:
    names = {str(p.obj_id): p.name for p in PART_SETS[args.parts]}
    parts = list(points[0]["clean_per_part"])
    header = ["arm", "method", "epochs", "training s", "clean MSSD", "bin MSSD",
              *(f"clean {names[p]}" for p in parts), "look-alike right share (clean / bin)"]
    rows = []
    for p in points:
        shares = [f"{p['look_alike_clean'][k]['right_share']:.2f} / "
                  f"{p['look_alike_bin'].get(k, {}).get('right_share', float('nan')):.2f} ({names[k]})"
                  for k in p["look_alike_clean"]]
        rows.append([p["arm"], p["representation"], p["epochs"], f"{p['training_s']:.0f}",
                     f"{100 * p['clean_mssd']:.1f}", f"{100 * p['bin_mssd']:.1f}",
                     *(f"{100 * p['clean_per_part'][k]:.1f}" for k in parts), "; ".join(shares) or "–"])
    return "\n".join([
        f"# Pretrained start against random weights ({args.parts} parts)", "",
        f"`python -m experiments.pretrained_start {' '.join(args.argv)}`", "",
        f"Start: {start_text}. Parts: the {args.parts} parts that take the full code "
        f"({', '.join(names[p] for p in parts)}); {args.images} training images a part and {args.scenes} bin scenes; "
        f"scored on {VALIDATION_IMAGES} clean images a part (seed {CLEAN_VALIDATION_SEED}) and {VALIDATION_SCENES} "
        f"bin scenes (seed {CLUTTERED_VALIDATION_SEED}). The look-alike share: of the estimates within 15 deg of the "
        "truth up to the part's look-alike poses, those within 15 deg of the truth itself.", "",
        markdown_table(header, rows), "", machine_line(machine()), ""])


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--start", type=Path, required=True, help="a start of popcode-train pretrain")
    parser.add_argument("--epochs", type=int, nargs="+", default=[3, 6, 12])
    parser.add_argument("--parts", choices=list(PART_SETS), default="validation")
    parser.add_argument("--images", type=int, default=2000)
    parser.add_argument("--scenes", type=int, default=150)
    parser.add_argument("--representations", nargs="+", default=[Representation.POPULATION_CODE])
    parser.add_argument("--arms", nargs="+", choices=list(ARMS), default=["scratch", "pretrained"])
    parser.add_argument("--work", type=Path, default=Path("runs/pretrained_start"))
    parser.add_argument("--name", default="pretrained-start")
    args = parser.parse_args(argv)
    args.argv = list(argv) if argv is not None else sys.argv[1:]
    start = read_start(args.start)
    parts, code, splits = render(args.work, args.parts, args.images, args.scenes)
    points = [point(args.work, parts, code, splits, arm, args.start, epochs, representation)
              for representation in args.representations for epochs in args.epochs for arm in args.arms]
    write_results(RESULTS, args.name, {"start": start.card, "points": points},
                  to_markdown(points, f"`{args.start.name}` ({describe(start)})", args))
    return points


if __name__ == "__main__":
    run_command("experiments.pretrained_start", main)
