"""Accuracy against training budget: MSSD on a validation split after N crop-updates of one recipe.

    python -m experiments.budget_curve [--config trainer/configs/quick.toml] [--set KEY=VALUE ...]
        [--epochs 5 10 20 40] [--images 1000] [--obj-ids 3 4 5 6] [--work DIR] [--name NAME]

Renders the built-in parts into a training split (seed 0) and a separate validation split
(seed 2000; the demo's test split, seed 1000, is never read here), trains one model with the
config (its data paths and output folder replaced), and after each budget in ``--epochs``
scores the last checkpoint on the validation split. The run is extended by resuming with more
epochs (``train.epochs`` may grow on resume), so a curve costs its longest point only; with
the constant learning rate of the quick recipe every point equals a run of that length.

Each point records the crop-updates, the training seconds spent so far, MSSD overall and per
part and the median rotation error; ``--work`` keeps the splits and runs, so an interrupted
curve resumes. Results: ``bench/results/budget-<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_json_atomic
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.train.config import Config, load_config
from popcode_trainer.train.training_data import build_training_data
from tools.command import run_command
from tools.experiment import (
    TRAIN_SEED,
    VALIDATION_SEED,
    score_last_checkpoint,
    train_run,
    training_config,
    training_so_far,
)
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results


def _point(config: Config, run_dir: Path, validation_split: Path, obj_ids: Sequence[int]) -> dict[str, Any]:
    result = score_last_checkpoint(run_dir, config.train.representation, validation_split, obj_ids)
    return {
        "epochs": config.train.epochs,
        **training_so_far(run_dir),
        "mssd": result.groups["All objects"]["MSSD"],
        "mssd_with_ambiguity": result.groups["With ambiguity"]["MSSD"],
        "mssd_without_ambiguity": result.groups["Without ambiguity"]["MSSD"],
        "mssd_per_object": {str(obj): scores["MSSD"] for obj, scores in sorted(result.per_object.items())},
    }


def curve(base: Config, epochs: Sequence[int], images: int, obj_ids: Sequence[int], work: Path,
          name: str) -> list[dict[str, Any]]:
    train_split = render_builtin_split(work / "train", images, seed=TRAIN_SEED, obj_ids=obj_ids,
                                       random_position=True, progress=True)
    validation_split = render_builtin_split(work / "validation", max(20, images // 10), seed=VALIDATION_SEED,
                                            obj_ids=obj_ids, random_position=True, progress=True)
    run_dir = work / "runs" / name
    scored = run_dir / "points.json"  # points already scored: an interrupted curve skips them
    points = json.loads(scored.read_text(encoding="utf-8")) if scored.exists() else []
    for budget in sorted(set(epochs) - {p["epochs"] for p in points}):
        if points and budget < max(p["epochs"] for p in points):
            raise PopcodeError(f"{run_dir} has trained past {budget} epochs; score smaller budgets in a new --work")
        config = training_config(base, run_dir, budget, splits=(str(train_split),),
                                 models_dir=str(train_split / BUILTIN_MODELS_FOLDER), obj_ids=())
        train_run(config, build_training_data(config))
        points.append(_point(config, run_dir, validation_split, obj_ids))
        write_json_atomic(scored, points)
        print(f"{budget} epochs: MSSD {100 * points[-1]['mssd']:.1f} %", flush=True)
    return sorted((p for p in points if p["epochs"] in epochs), key=lambda p: p["epochs"])


def to_markdown(name: str, points: Sequence[dict[str, Any]], overrides: Sequence[str], images: int,
                machine_description: dict[str, Any]) -> str:
    obj_ids = list(points[0]["mssd_per_object"])
    rows = [[str(p["epochs"]), f"{p['crop_updates']:,}", f"{p['training_s'] / 60:.1f}", f"{100 * p['mssd']:.1f}",
             f"{100 * p['mssd_with_ambiguity']:.1f}", f"{100 * p['mssd_without_ambiguity']:.1f}",
             f"{p['held_out_median_deg']:.1f}",
             *(f"{100 * p['mssd_per_object'][obj]:.1f}" for obj in obj_ids)] for p in points]
    header = ["epochs", "crop-updates", "training min", "MSSD %", "ambiguous", "not ambiguous",
              "median error ° (held-out training images)",
              *(f"obj {obj}" for obj in obj_ids)]
    return "\n".join([
        f"# Accuracy against training budget: {name}", "",
        f"`python -m experiments.budget_curve` with {images} training images per part, overrides: "
        f"{', '.join(f'`{o}`' for o in overrides) or 'none'}. MSSD (BOP19 recall, rotation only, GT translation) "
        f"on the validation split (seed {VALIDATION_SEED}), last checkpoint of one run extended epoch budget by "
        "epoch budget.",
        "", machine_line(machine_description), "", markdown_table(header, rows),
    ])


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("trainer/configs/quick.toml"))
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one setting of the config (repeatable)")
    parser.add_argument("--epochs", nargs="+", type=int, default=[5, 10, 20, 40], help="budgets to score")
    parser.add_argument("--images", type=int, default=1000, help="training images per part")
    parser.add_argument("--obj-ids", nargs="+", type=int, default=[3, 4, 5, 6], help="built-in parts (one model)")
    parser.add_argument("--work", type=Path, default=Path("runs/budget_curve"), help="splits and runs (resumable)")
    parser.add_argument("--name", default="quick", help="name of the curve (results file budget-<name>)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    base = load_config(args.config, args.overrides)
    points = curve(base, args.epochs, args.images, args.obj_ids, args.work, args.name)
    payload = {"config": str(args.config), "overrides": args.overrides, "images_per_object": args.images,
               "obj_ids": args.obj_ids, "points": points}
    write_results(args.out, f"budget-{args.name}", payload,
                  to_markdown(args.name, points, args.overrides, args.images, machine()))
    return points


if __name__ == "__main__":
    run_command("experiments.budget_curve", lambda: 0 if main() else 1)
