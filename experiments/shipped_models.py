"""Train the shipped models: the medium demo's data, network and recipe, the population code alone, its epochs
fitted to a time budget, exported as the demo exports them (ONNX fp32, static int8, confidence calibrator).

    python -m experiments.shipped_models [--minutes 8] [--out runs/shipped] [--copy-to DIR] [--images N] [--scenes N]
        [--test-images N] [--compile auto|on|off] [--group OBJ_ID ...] [--box-noise-p P] [--scene-share S]
        [--network NAME] [--traced-images N --traced-share S] [--render-only]

Made for a lent GPU machine, whose lease is minutes: ``popcode-train demo --size medium --minutes M`` trains the
single-variable baseline beside every model and spends the budget's tail on its evaluation, which the shipped
models need neither of (they are scored on splits no run uses: ``models/README.md``). Here the whole budget
goes to the population code's models, one per object group, each trained as the demo trains it (same split,
seeds, code, mix of scene crops; first epochs timed, then all resumed to the fitted epochs). ``--copy-to``
receives each model's ONNX files and training curve as soon as it is exported, so a run cut short keeps what
it finished, and at the end ``run.json``: the machine (CPU flags, cores, load, library versions), the GPU, the
arguments, the epochs and each step's seconds. ``--images`` / ``--scenes`` / ``--test-images`` change the data
(shrink it for a check of the script itself); ``--group`` trains only the model of the group that holds those
parts (the whole budget to it; the renders stay those of every part); ``--box-noise-p`` changes the share of crops
cut from detector-like boxes; ``--scene-share`` the share of an epoch's crops cut from the training scenes;
``--network`` trains another of :data:`tools.recipes.NETWORKS` (the trunk's width); ``--traced-images`` path
traces that many further single-part images a part (``popcode-train path-trace``) and ``--traced-share`` gives
them that share of every epoch's crops (bench/results/path-traced.md).
``--render-only`` renders the data and stops: variants trained side by side on one GPU (its eager step leaves it
mostly idle) then each get an ``--out`` holding links to these splits. Rerunning with the same ``--out``
resumes, as the demo does. ``--compile on`` compiles the step (on a GPU with CUDA graphs: the eager step of
this network is bound by its kernel launches, ``bench/results/cuda-step.md``).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from popcode_runtime.base.files import copy_file_atomic, write_json_atomic
from popcode_trainer.demo.epoch_budget import FIT_FILE
from popcode_trainer.demo.parts import BUILTIN
from popcode_trainer.demo.plan import FIRST_EPOCHS, StagePlan, plan
from popcode_trainer.demo.report import POPCODE
from popcode_trainer.demo.run import fit_epochs, prepare_parts, train_models
from popcode_trainer.demo.steps import render_splits, run_dir
from popcode_trainer.train.run_files import METRICS_FILE
from tools.command import bad_input_exits
from tools.recipes import shipped_arguments, shipped_size
from tools.report import machine

RUN_FILE = "run.json"  # beside the copied exports


def training_plan(stages: StagePlan) -> StagePlan:
    """The demo's plan without its evaluation steps: rendering, the first epochs and the training."""
    kept = [(name, seconds) for name, seconds in stages.estimates.items()
            if name in ("render", FIRST_EPOCHS) or name.startswith("train ")]
    return StagePlan(kept)


def copy_exports(folder: Path, destination: Path) -> None:
    """A model's ONNX files and its training curve into ``destination/<run folder name>/``."""
    target = destination / folder.name
    target.mkdir(parents=True, exist_ok=True)
    for path in [*sorted(folder.glob("*.onnx")), folder / METRICS_FILE]:
        copy_file_atomic(path, target / path.name)


def main(argv: Sequence[str] | None = None) -> int:
    args, parser = shipped_arguments(argv, __doc__.split("\n\n")[0])
    started = time.perf_counter()
    with bad_input_exits("experiments.shipped_models"):  # the renders stay for a rerun
        return _train(args, parser, started, list(sys.argv[1:] if argv is None else argv))


def _train(args: argparse.Namespace, parser: argparse.ArgumentParser, started: float, arguments: list[str]) -> int:
    """Render, time the first epochs, fit the epochs, train and export every model of ``args`` (``arguments``:
    the command line, for ``run.json``)."""
    demo, size = shipped_size(args)
    parts, codes = prepare_parts(BUILTIN, size.config.code)
    if args.group:
        codes = [g for g in codes if set(args.group) & set(g.obj_ids)]
        if not codes:
            parser.error(f"--group {args.group}: no built-in part of that id")
    stages = training_plan(plan(size, [list(g.obj_ids) for g in codes], len(parts.obj_ids), fit_epochs=True))
    with stages.stage("render"):
        train_split, _ = render_splits(size, args.out, parts=parts)
    if args.render_only:
        print(f"rendered in {(time.perf_counter() - started) / 60:.1f} min", flush=True)
        return 0
    with stages.stage(FIRST_EPOCHS):
        fit = fit_epochs(size, demo, codes, train_split, args.out, started, stages)
    print(f"{fit.epochs} epochs (first epochs {fit.first_epoch_seconds}; {fit.seconds_left:.0f} s left for "
          "training)", flush=True)
    size = size.with_epochs(fit.epochs)
    if args.copy_to:
        args.copy_to.mkdir(parents=True, exist_ok=True)
        copy_file_atomic(args.out / FIT_FILE, args.copy_to / FIT_FILE)
    for group in codes:
        train_models(size, [group], train_split, args.out, stages)
        if args.copy_to:
            copy_exports(run_dir(args.out, POPCODE, group.obj_ids), args.copy_to)
    print(f"done in {(time.perf_counter() - started) / 60:.1f} min: {dict(stages.done)}", flush=True)
    if args.copy_to:  # what a results file must name: the machine, the libraries, the command, the steps' seconds
        write_json_atomic(args.copy_to / RUN_FILE, {
            "machine": machine(), "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
            "arguments": arguments, "epochs": fit.epochs,
            "step_seconds": dict(stages.done)})
    return 0


if __name__ == "__main__":
    sys.exit(main())
