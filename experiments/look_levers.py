"""Which lever closes the gap between the rasteriser's look and a path tracer's, per CPU-minute.

    python -m experiments.look_levers [--levers rasterised path-traced-share grain] [--images 2000] [--scenes 150]
        [--traced-images 500] [--crop-updates 128000] [--obj-ids 3 4 5 6] [--work runs/look_levers]
        [--validation runs/path_traced] [--name look-levers]

Each lever trains one model of ``--obj-ids`` from scratch with the quick demo's recipe (``small_config``: 642 x 36
code, batch 32, allocentric, a quarter of the crops from training scenes) for the same crop-updates, and is scored
on the four validation splits of :mod:`experiments.path_traced_gap` (clean and bin, rendered and path traced;
run it first: its ``--work`` is ``--validation`` here). The levers:

- ``rasterised``: today's data, the reference.
- ``path-traced-share``: a quarter of the crops from single-part images path traced once (``popcode-train
  path-trace`` of a separate render, seed 7, other material and light draws than the validation's), cached.
- ``grain``: the paper's Gaussian grain stronger and more often (``data.noise_sigma`` 0.06, ``data.noise_p`` 0.8),
  free at training time.
- ``path-traced-scenes``: ``path-traced-share`` with the training scenes path traced too (8 samples a pixel, the
  rasterised scenes replaced), so that the bin's crops also show metal, soft shadows and interreflections.

Scores are paired per instance against ``rasterised`` (bootstrap 95 % intervals), so a lever's gain is read on
the same instances. ``--work`` keeps splits, runs and scores: a rerun resumes.
Results: ``bench/results/<name>.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

from experiments.path_traced_gap import LOOKS, SPLITS, instance_scores, paired
from popcode_runtime.base.files import read_json, write_json_atomic
from popcode_trainer.cli import main as trainer
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.demo.sizes import SCENE_SHARE
from popcode_trainer.demo.steps import TRAIN_SCENES_SEED_OFFSET, small_config
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.train.run_files import LAST_CHECKPOINT
from popcode_trainer.train.training_data import build_training_data
from tools.command import run_command
from tools.experiment import TRAIN_SEED, train_run, training_config, training_so_far
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

LEVERS = ("rasterised", "path-traced-share", "grain", "path-traced-scenes")
TRACED_SEED = 7  # of the single parts path traced for training: no validation image among them
TRACED_SHARE = 0.25  # of every epoch's crops, taken from the single parts' share
SCENE_SAMPLES = 8  # a 720 x 540 scene path traces in seconds at 8 samples a pixel, not half a minute at 32
GRAIN = {"noise_sigma": 0.06, "noise_p": 0.8}
TRACE_SECONDS = "path_trace_seconds.json"  # in --work: what tracing the training splits cost


def training_splits(work: Path, images: int, scenes: int, traced_images: int, obj_ids: Sequence[int],
                    levers: Sequence[str]) -> dict[str, Any]:
    """Render (and, for the path-traced share, path trace) the training splits; returns their folders and the
    seconds the path tracer took."""
    single = render_builtin_split(work / "train", images, seed=TRAIN_SEED, obj_ids=obj_ids, random_position=True,
                                  progress=True)
    scene_split = render_cluttered_test_split(work / "train_scenes", scenes, progress=True, obj_ids=obj_ids,
                                              seed=TRAIN_SEED + TRAIN_SCENES_SEED_OFFSET)
    splits: dict[str, Any] = {"single": single, "scenes": scene_split}
    if "path-traced-share" in levers or "path-traced-scenes" in levers:
        source = render_builtin_split(work / "train_for_tracing", traced_images, seed=TRACED_SEED, obj_ids=obj_ids,
                                      random_position=True, progress=True)
        splits["traced"] = _path_trace(source, work / "train_traced", 32, work)
    if "path-traced-scenes" in levers:
        splits["traced_scenes"] = _path_trace(scene_split, work / "train_scenes_traced", SCENE_SAMPLES, work)
    return splits


def _path_trace(source: Path, out: Path, samples: int, work: Path) -> Path:
    """``popcode-train path-trace`` of ``source`` (look seed 1); the seconds an image it took, where it traced
    any, are kept in ``work/TRACE_SECONDS`` (a resumed trace's time would say nothing)."""
    done = len(list(out.glob("*/.popcode_records/*.json")))
    start = time.perf_counter()
    if trainer(["path-trace", "--split", str(source), "--out", str(out), "--seed", "1", "--samples",
                str(samples)]) != 0:
        raise SystemExit(f"path tracing {source} failed")
    traced = len(list(out.glob("*/.popcode_records/*.json"))) - done
    if traced and done == 0:
        seconds = read_json(work / TRACE_SECONDS) if (work / TRACE_SECONDS).is_file() else {}
        seconds[out.name] = {"images": traced, "seconds_an_image": (time.perf_counter() - start) / traced}
        write_json_atomic(work / TRACE_SECONDS, seconds)
    return out


def lever_config(lever: str, splits: dict[str, Any], run_dir: Path, epochs: int, obj_ids: Sequence[int]) -> Any:
    base = small_config(epochs=epochs, n_axes=642, n_angles=36)
    single, scenes = str(splits["single"]), str(splits["scenes"])
    data: dict[str, Any] = {"splits": (single, scenes), "split_weights": (1.0 - SCENE_SHARE, SCENE_SHARE)}
    if lever in ("path-traced-share", "path-traced-scenes"):
        if lever == "path-traced-scenes":
            scenes = str(splits["traced_scenes"])
        data = {"splits": (single, str(splits["traced"]), scenes),
                "split_weights": (1.0 - SCENE_SHARE - TRACED_SHARE, TRACED_SHARE, SCENE_SHARE)}
    elif lever == "grain":
        data.update(GRAIN)
    base = replace(base, data=replace(base.data, obj_ids=tuple(obj_ids), cache_dir=str(run_dir / "crop_cache")))
    return training_config(base, run_dir, epochs, models_dir=str(splits["single"] / BUILTIN_MODELS_FOLDER), **data)


def train_lever(lever: str, splits: dict[str, Any], work: Path, crop_updates: int,
                obj_ids: Sequence[int]) -> dict[str, Any]:
    run_dir = work / "runs" / lever
    data = build_training_data(lever_config(lever, splits, run_dir, 1, obj_ids))
    epochs = max(1, round(crop_updates / len(data.train_set)))
    if not (run_dir / "done.json").is_file():
        train_run(lever_config(lever, splits, run_dir, epochs, obj_ids), data)
        write_json_atomic(run_dir / "done.json", {"epochs": epochs})
    return {"epochs": epochs, "epoch_crops": len(data.train_set), **training_so_far(run_dir)}


def paired_gain(reference: dict[tuple, float], lever: dict[tuple, float]) -> dict[str, Any]:
    result = paired(reference, lever)
    return {"mssd": 100.0 * result.second, "gain": 100.0 * result.difference,
            "gain_interval": [100.0 * v for v in result.interval]}


def _cell(result: dict[str, Any], reference: bool) -> str:
    if reference:
        return f"{result['mssd']:.1f}"
    low, high = result["gain_interval"]
    return f"{result['mssd']:.1f} ({result['gain']:+.1f} [{low:+.1f}, {high:+.1f}])"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--levers", nargs="+", choices=LEVERS, default=list(LEVERS))
    parser.add_argument("--images", type=int, default=2000, help="rasterised single-part images a part")
    parser.add_argument("--scenes", type=int, default=150, help="training scenes")
    parser.add_argument("--traced-images", type=int, default=500, help="path-traced single-part images a part")
    parser.add_argument("--crop-updates", type=int, default=128000, help="training budget of every lever")
    parser.add_argument("--obj-ids", nargs="+", type=int, default=[3, 4, 5, 6], help="parts of one model")
    parser.add_argument("--work", type=Path, default=Path("runs/look_levers"))
    parser.add_argument("--validation", type=Path, default=Path("runs/path_traced"),
                        help="the --work of experiments.path_traced_gap: its four validation splits")
    parser.add_argument("--name", default="look-levers")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if "rasterised" not in args.levers:
        parser.error("--levers must include rasterised: every lever is paired against it")
    splits = training_splits(args.work, args.images, args.scenes, args.traced_images, args.obj_ids, args.levers)
    trained, scores = {}, {}
    for lever in args.levers:
        trained[lever] = train_lever(lever, splits, args.work, args.crop_updates, args.obj_ids)
        checkpoint = args.work / "runs" / lever / LAST_CHECKPOINT
        scores[lever] = {(split, look): instance_scores(args.validation, split, look, f"lever-{lever}", [checkpoint],
                                                        args.obj_ids) for split in SPLITS for look in LOOKS}
    results = {lever: {f"{split} {look}": paired_gain(scores["rasterised"][(split, look)], by_split[(split, look)])
                       for split in SPLITS for look in LOOKS} for lever, by_split in scores.items()}
    columns = [f"{split} {look}" for split in SPLITS for look in LOOKS]
    rows = [[lever, str(trained[lever]["epochs"]), f"{trained[lever]['training_s'] / 60:.1f}",
             *(_cell(results[lever][column], lever == "rasterised") for column in columns)] for lever in args.levers]
    arguments = " ".join(sys.argv[1:] if argv is None else argv)
    trace_file = args.work / TRACE_SECONDS
    trace_seconds = read_json(trace_file) if trace_file.is_file() else {}
    markdown = "\n".join([
        f"# {args.name}: levers against the rasteriser's look, objects {' '.join(map(str, args.obj_ids))}", "",
        f"`python -m experiments.look_levers {arguments}`. MSSD % (argmax, ground-truth boxes, instances >= 10 % "
        "visible) on the validation splits of `experiments.path_traced_gap`; in brackets the gain over "
        "`rasterised` on the same instances with its bootstrap 95 % interval.", "",
        markdown_table(["lever", "epochs", "training min", *(f"{c} MSSD %" for c in columns)], rows), "",
        f"Path tracing the training splits: {json.dumps(trace_seconds)} (measured when each was traced from "
        f"scratch). {machine_line(machine())}",
    ])
    write_results(args.out, args.name, {"arguments": arguments, "trained": trained, "results": results,
                                        "path_trace_seconds": trace_seconds}, markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    run_command("experiments.look_levers", main)
