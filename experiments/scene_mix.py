"""How much of a training epoch should be cluttered scenes: MSSD on a cluttered and a clean *validation* split
against the share of scene crops, at an equal number of crop-updates.

    python -m experiments.scene_mix [--config trainer/configs/quick.toml] [--set KEY=VALUE ...]
        [--shares 0 0.25 0.5 0.75] [--images 500] [--scenes 300] [--crop-updates 24000]
        [--objects builtin|MODELS_DIR] [--obj-ids 3 4 5 6] [--work DIR] [--name NAME]

Renders the built-in parts (or those of a BOP models folder, ``--objects``: e.g. the validation parts that
``python -m tools.own_parts validation`` writes, to judge a recipe on parts no choice was tuned on) alone (seed 0,
as the demo's training split) and in cluttered bin scenes (seed 3000, as the demo's training scenes), and two validation
splits no recipe is reported on: clean single parts (seed 5000) and cluttered scenes (seed 4000). The demo's
test splits (seeds 1000 and 2000) are never read here. Each share trains one model from the config (``data.splits`` and
``data.split_weights`` replaced; share 0 trains on the single parts alone) for the epochs that give
``--crop-updates``, and scores its last checkpoint on both validation splits, the cluttered one per
visible-fraction bin. ``--work`` keeps splits and runs, so an interrupted comparison resumes.
Results: ``bench/results/scene-mix-<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from popcode_runtime.base.files import write_json_atomic
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.demo.parts import BUILTIN, load_parts
from popcode_trainer.demo.steps import TRAIN_SCENES_SEED_OFFSET
from popcode_trainer.eval.pipeline.evaluate import MethodResult
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.recall import VISIBILITY_BINS
from popcode_trainer.train.config import Config, load_config
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
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

DETECTOR_BOXES = "detector"
VALIDATION_SCENES, VALIDATION_IMAGES = 80, 40


def _config(base: Config, single: Path, scenes: Path, share: float, run_dir: Path, epochs: int) -> Config:
    splits, weights = ((str(single),), ()) if share == 0 else ((str(single), str(scenes)), (1.0 - share, share))
    return training_config(base, run_dir, epochs, splits=splits, split_weights=weights,
                           models_dir=str(single / BUILTIN_MODELS_FOLDER))


def _scores(result: MethodResult) -> dict[str, Any]:
    return {"mssd": result.groups["All objects"]["MSSD"],
            "mssd_per_object": {str(obj): s["MSSD"] for obj, s in sorted(result.per_object.items())},
            "by_visibility": {label: {"mssd": s["MSSD"], "instances": s["instances"]}
                              for label, s in result.by_visibility.items()}}


def _score(run_dir: Path, name: str, split_dir: Path, obj_ids: Sequence[int], boxes: str = "none") -> dict[str, Any]:
    return _scores(score_last_checkpoint(run_dir, name, split_dir, obj_ids, boxes))


@dataclass(frozen=True)
class Splits:
    """Where the comparison's renders lie: two training splits and two validation splits."""

    single: Path
    scenes: Path
    clean: Path
    cluttered: Path


def render_all(objects: str | Path, obj_ids: Sequence[int], images: int, scenes: int, work: Path) -> Splits:
    """Render (or complete) the four splits of ``obj_ids``: built-in parts, or those of the models folder
    ``objects`` (rendered as ``popcode-train demo --objects`` renders them; only ``obj_ids`` appear)."""
    scene_seed = TRAIN_SEED + TRAIN_SCENES_SEED_OFFSET
    if objects == BUILTIN:
        return Splits(
            render_builtin_split(work / "train", images, seed=TRAIN_SEED, obj_ids=obj_ids, random_position=True,
                                 progress=True),
            render_cluttered_test_split(work / "train_scenes", scenes, progress=True, obj_ids=obj_ids,
                                        seed=scene_seed),
            render_builtin_split(work / "val_clean", VALIDATION_IMAGES, seed=CLEAN_VALIDATION_SEED, obj_ids=obj_ids,
                                 random_position=True, progress=True),
            render_cluttered_test_split(work / "val_cluttered", VALIDATION_SCENES, progress=True, obj_ids=obj_ids,
                                        seed=CLUTTERED_VALIDATION_SEED))
    parts = load_parts(objects)
    if missing := sorted(set(obj_ids) - set(parts.obj_ids)):
        raise SystemExit(f"--obj-ids {missing} are not in {objects} (objects {parts.obj_ids})")
    chosen = replace(parts, models_info={i: parts.models_info[i] for i in obj_ids},
                     reach_mm={i: r for i, r in parts.reach_mm.items() if i in obj_ids})
    return Splits(chosen.render_split(work / "train", images, TRAIN_SEED, True),
                  chosen.render_scenes(work / "train_scenes", scenes, scene_seed, True),
                  chosen.render_split(work / "val_clean", VALIDATION_IMAGES, CLEAN_VALIDATION_SEED, True),
                  chosen.render_scenes(work / "val_cluttered", VALIDATION_SCENES, CLUTTERED_VALIDATION_SEED, True))


def compare(base: Config, shares: Sequence[float], splits: Splits, crop_updates: int, obj_ids: Sequence[int],
            work: Path, name: str) -> list[dict[str, Any]]:
    single, scene_split, clean, cluttered = splits.single, splits.scenes, splits.clean, splits.cluttered
    rows = []
    for share in shares:
        run_dir = work / "runs" / f"{name}-share{share:g}"
        scored = run_dir / "scores.json"
        if scored.exists():  # an interrupted comparison skips what it scored
            row = json.loads(scored.read_text(encoding="utf-8"))
            if "cluttered_detector_boxes" not in row:  # scored before detector-like boxes were
                row["cluttered_detector_boxes"] = _score(run_dir, name, cluttered, obj_ids, DETECTOR_BOXES)
                write_json_atomic(scored, row)
            rows.append(row)
            continue
        config = _config(base, single, scene_split, share, run_dir, 1)
        data = build_training_data(config)
        epochs = max(1, round(crop_updates / len(data.train_set)))
        config = _config(base, single, scene_split, share, run_dir, epochs)
        train_run(config, data)
        row = {"share": share, "epochs": epochs, "epoch_crops": len(data.train_set), **training_so_far(run_dir),
               "clean": _score(run_dir, name, clean, obj_ids), "cluttered": _score(run_dir, name, cluttered, obj_ids),
               "cluttered_detector_boxes": _score(run_dir, name, cluttered, obj_ids, DETECTOR_BOXES)}
        write_json_atomic(scored, row)
        rows.append(row)
        print(f"share {share:g}: MSSD clean {100 * row['clean']['mssd']:.1f} %, cluttered "
              f"{100 * row['cluttered']['mssd']:.1f} %", flush=True)
    return rows


def to_markdown(name: str, rows: Sequence[dict[str, Any]], arguments: str, description: dict[str, Any]) -> str:
    bins = [label for label, _, _ in VISIBILITY_BINS]
    obj_ids = list(rows[0]["cluttered"]["mssd_per_object"])
    header = ["scene share", "epochs", "crop-updates", "training min", "clean MSSD %", "cluttered MSSD %",
              "cluttered, detector boxes",
              *(f"cluttered {label}" for label in bins), *(f"cluttered obj {obj}" for obj in obj_ids)]
    table = [[f"{r['share']:g}", str(r["epochs"]), f"{r['crop_updates']:,}", f"{r['training_s'] / 60:.1f}",
              f"{100 * r['clean']['mssd']:.1f}", f"{100 * r['cluttered']['mssd']:.1f}",
              f"{100 * r['cluttered_detector_boxes']['mssd']:.1f}",
              *(f"{100 * r['cluttered']['by_visibility'][b]['mssd']:.1f}" for b in bins),
              *(f"{100 * r['cluttered']['mssd_per_object'][o]:.1f}" for o in obj_ids)] for r in rows]
    counts = ", ".join(f"{b}: {rows[0]['cluttered']['by_visibility'][b]['instances']:.0f}" for b in bins)
    return "\n".join([
        f"# Share of cluttered scenes in training: {name}", "",
        f"`python -m experiments.scene_mix {arguments}`. MSSD (BOP19 recall, rotation only, ground-truth boxes and "
        f"translation) of each model's last checkpoint on two validation splits: clean single parts (seed "
        f"{CLEAN_VALIDATION_SEED}) and cluttered bin scenes with the industrial sensor (seed "
        f"{CLUTTERED_VALIDATION_SEED}; instances >= 10 % visible, per visible-fraction bin: {counts}). Training: "
        f"single parts (seed {TRAIN_SEED}) mixed with scenes (seed {TRAIN_SEED + TRAIN_SCENES_SEED_OFFSET}) at "
        "each share, at about the same crop-updates. \"detector boxes\": the cluttered split again with each crop cut "
        f"from a detector-like box (box-noise preset `{DETECTOR_BOXES}`, IoU about 0.75).", "",
        machine_line(description), "", markdown_table(header, table),
    ])


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("trainer/configs/quick.toml"))
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one setting of the config (repeatable)")
    parser.add_argument("--shares", nargs="+", type=float, default=[0.0, 0.25, 0.5, 0.75],
                        help="shares of scene crops in an epoch to compare")
    parser.add_argument("--images", type=int, default=500, help="single-part training images per part")
    parser.add_argument("--scenes", type=int, default=300, help="training scenes")
    parser.add_argument("--crop-updates", type=int, default=24000, help="training budget of every model")
    parser.add_argument("--objects", default=BUILTIN,
                        help="'builtin' (default) or a BOP models folder of your own parts")
    parser.add_argument("--obj-ids", nargs="+", type=int, default=[3, 4, 5, 6], help="parts of one model")
    parser.add_argument("--work", type=Path, default=Path("runs/scene_mix"), help="splits and runs (resumable)")
    parser.add_argument("--name", default="quick", help="name of the comparison (results file scene-mix-<name>)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if any(not 0.0 <= share < 1.0 for share in args.shares):
        parser.error("--shares must lie in [0, 1)")
    base = load_config(args.config, args.overrides)
    splits = render_all(args.objects, args.obj_ids, args.images, args.scenes, args.work)
    rows = compare(base, args.shares, splits, args.crop_updates, args.obj_ids, args.work, args.name)
    arguments = " ".join(sys.argv[1:] if argv is None else argv)
    payload = {"arguments": arguments, "config": str(args.config), "overrides": args.overrides, "rows": rows}
    write_results(args.out, f"scene-mix-{args.name}", payload, to_markdown(args.name, rows, arguments, machine()))
    return rows


if __name__ == "__main__":
    run_command("experiments.scene_mix", lambda: 0 if main() else 1)
