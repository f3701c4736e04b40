"""What the rasteriser's look costs: models scored on validation splits and on the same splits path traced.

    python -m experiments.path_traced_gap [--method NAME=MODEL[,MODEL...] ...] [--baseline NAME] [--detector-boxes]
        [--work runs/path_traced] [--images 20] [--scenes 20] [--samples 32] [--name path-traced-gap]

Renders the project's validation splits (clean single parts, seed 5000; a bin with the industrial camera, seed
4000: no recipe is reported on a test split), path traces them (``popcode-train path-trace``: same scenes,
poses and sensor draw, physically based metals, plastics and lights), and scores each method on all four with
``popcode-train evaluate`` (ground-truth boxes, instances at least 10 % visible, argmax). Since the ground truth
is shared, every instance is scored twice: the drop is paired, with a bootstrap 95 % interval over instances.
The default method is the shipped models. ``--baseline`` pairs every other method with that one on each split
and look (a refresh's gain, instance by instance). ``--detector-boxes`` crops every instance from a detector-like
box instead of its true one (``evaluate --box-noise detector --box-noise-seed 0``: the same boxes for every
method). ``--work`` keeps the splits and scores: a rerun resumes.
Results: ``bench/results/<name>.{json,md}``, with the machine and the path tracer's seconds an image.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from popcode_trainer.cli import main as trainer
from popcode_trainer.data.bop import load_models_info
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.metrics.paired import PairedDifference, instance_mssd_scores, paired_difference
from tools.command import run_command
from tools.paths import RESULTS, ROOT, SHIPPED_MODELS
from tools.report import machine, machine_line, write_results

SHIPPED = "shipped=" + ",".join(str(path.relative_to(ROOT)) for path in SHIPPED_MODELS)
SPLITS = {  # name: render options of the validation split
    "clean": ["--images", "{images}", "--seed", "5000"],
    "bin": ["--scenes", "{scenes}", "--seed", "4000", "--sensor", "industrial"],
}
LOOKS = ("rendered", "path_traced")
MIN_VISIB_FRACT = "0.1"
DETECTOR_BOXES = ("--box-noise", "detector", "--box-noise-seed", "0")
VISIBLE_BANDS = ((0.9, 1.0), (0.6, 0.9), (0.1, 0.6))  # the bin's drop by visible fraction: [low, high)


def _run(argv: list[str]) -> None:
    if trainer(argv) != 0:
        raise SystemExit(f"popcode-train {' '.join(argv)} failed")


def prepare_splits(work: Path, images: int, scenes: int, samples: int) -> dict[str, float]:
    """Render and path trace each validation split (resumes); returns the path tracer's seconds an image."""
    seconds = {}
    for split, options in SPLITS.items():
        rendered, traced = work / f"{split}_rendered", work / f"{split}_path_traced"
        _run(["render", "--objects", "builtin", "--out", str(rendered), "--quiet",
              *[option.format(images=images, scenes=scenes) for option in options]])
        start = time.perf_counter()
        before = len(list(traced.glob("*/.popcode_records/*.json")))
        _run(["path-trace", "--split", str(rendered), "--out", str(traced), "--samples", str(samples), "--quiet"])
        traced_now = len(list(traced.glob("*/.popcode_records/*.json"))) - before
        if traced_now:
            seconds[split] = (time.perf_counter() - start) / traced_now
    return seconds


def instance_scores(work: Path, split: str, look: str, method: str, models: Sequence[str | Path],
                    obj_ids: Sequence[int] = (), options: Sequence[str] = ()) -> dict[tuple, float]:
    """Each instance's MSSD score (the share of BOP's thresholds its error is below) of ``obj_ids`` (default:
    the models'), keyed by its identity, with more ``evaluate`` options (e.g. detector-like boxes); scored once
    into ``work/scores`` (delete it to score again)."""
    out = work / "scores" / f"{method}_{split}_{look}"
    errors = out / f"errors_{method}.csv"
    if not errors.is_file():
        _run(["evaluate", "--split", str(work / f"{split}_{look}"),
              "--models-dir", str(work / f"{split}_rendered" / "models"), "--min-visib-fract", MIN_VISIB_FRACT,
              "--no-vsd", "--out", str(out), "--overwrite", *options,
              *(["--obj-ids", *map(str, obj_ids)] if obj_ids else []),
              *[option for _ in models for option in ("--name", method)], *map(str, models)])
    diameters = {obj_id: float(info["diameter"]) for obj_id, info in
                 load_models_info(work / f"{split}_rendered" / "models").items()}
    with errors.open() as handle:
        rows = list(csv.DictReader(handle))
    scores = instance_mssd_scores(np.array([float(row["mssd_mm"]) for row in rows]),
                                  np.array([int(row["obj_id"]) for row in rows]), diameters)
    return {(int(row["scene_id"]), int(row["im_id"]), int(row["gt_index"])): float(score)
            for row, score in zip(rows, scores, strict=True)}


def visible_fractions(split: Path) -> dict[tuple, float]:
    """Each instance's visible fraction (``scene_gt_info.json``), keyed as :func:`instance_scores` keys them."""
    fractions = {}
    for info in split.glob("*/scene_gt_info.json"):
        for im_id, entries in json.loads(info.read_text()).items():
            for index, entry in enumerate(entries):
                fractions[int(info.parent.name), int(im_id), index] = float(entry["visib_fract"])
    return fractions


def drop_by_visibility(rendered: dict[tuple, float], traced: dict[tuple, float],
                       fractions: dict[tuple, float]) -> dict[str, dict[str, Any]]:
    """:func:`paired_drop` over the instances of each band of :data:`VISIBLE_BANDS` (the top one closed)."""
    bands = {}
    for low, high in VISIBLE_BANDS:
        keys = [k for k in rendered if low <= fractions[k] < high or high == 1.0 and fractions[k] == 1.0]
        if keys:
            bands[f"{low}-{high}"] = paired_drop({k: rendered[k] for k in keys}, {k: traced[k] for k in keys})
    return bands


def paired(first: dict[tuple, float], second: dict[tuple, float]) -> PairedDifference:
    """``second`` against ``first`` over the instances both scored (the same ones: the splits are paired)."""
    if first.keys() != second.keys():
        raise SystemExit("the two were scored on different instances: the splits are not paired")
    keys = sorted(first)
    return paired_difference(np.array([first[k] for k in keys]), np.array([second[k] for k in keys]))


def paired_drop(rendered: dict[tuple, float], traced: dict[tuple, float]) -> dict[str, Any]:
    """Both looks' MSSD (%), the drop and its bootstrap 95 % interval over the instances both scored."""
    result = paired(rendered, traced)
    return {"instances": result.instances, "rendered": 100.0 * result.first, "path_traced": 100.0 * result.second,
            "drop": 100.0 * result.difference, "drop_interval": [100.0 * v for v in result.interval]}


def _gain(result: PairedDifference) -> dict[str, Any]:
    return {"instances": result.instances, "gain": 100.0 * result.difference,
            "interval": [100.0 * v for v in result.interval]}


def _gain_table(baseline: str | None, gains: dict[str, dict[str, dict[str, Any]]]) -> list[str]:
    """Each method's paired MSSD gain over ``baseline`` (points, 95 % interval), a column per split and look."""
    if not gains:
        return []
    columns = [f"{split} {look}" for split in SPLITS for look in LOOKS]
    rows = [[method, *[f"{g[c]['gain']:+.1f} [{g[c]['interval'][0]:+.1f}, {g[c]['interval'][1]:+.1f}]"
                       for c in columns]] for method, g in gains.items()]
    return [f"Paired MSSD gain over `{baseline}` (points, 95 % interval), instance by instance:", "",
            markdown_table(["method", *[c.replace("_", "-") for c in columns]], rows), ""]


def parse_method(text: str) -> tuple[str, list[str]]:
    name, _, models = text.partition("=")
    if not name or not models:
        raise SystemExit(f"--method {text!r}: give NAME=MODEL[,MODEL...]")
    return name, models.split(",")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--method", action="append", help=f"NAME=MODEL[,MODEL...] (default {SHIPPED})")
    parser.add_argument("--work", type=Path, default=Path("runs/path_traced"))
    parser.add_argument("--images", type=int, default=20, help="clean images a part")
    parser.add_argument("--scenes", type=int, default=20, help="bin scenes")
    parser.add_argument("--samples", type=int, default=32, help="path tracer's samples a pixel")
    parser.add_argument("--baseline", metavar="NAME", help="a method to pair every other one with")
    parser.add_argument("--detector-boxes", action="store_true", help="crop from detector-like boxes")
    parser.add_argument("--name", default="path-traced-gap")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    methods = dict(parse_method(text) for text in (args.method or [SHIPPED]))
    if args.baseline is not None and args.baseline not in methods:
        parser.error(f"--baseline {args.baseline}: not one of the methods {sorted(methods)}")
    seconds = prepare_splits(args.work, args.images, args.scenes, args.samples)
    options, suffix = (DETECTOR_BOXES, "-detector-boxes") if args.detector_boxes else ((), "")
    scores = {(method, split, look): instance_scores(args.work, split, look, method + suffix, models,
                                                     options=options)
              for method, models in methods.items() for split in SPLITS for look in LOOKS}
    results = {method: {split: paired_drop(*(scores[method, split, look] for look in LOOKS)) for split in SPLITS}
               for method in methods}
    fractions = visible_fractions(args.work / "bin_rendered")
    by_visibility = {method: drop_by_visibility(*(scores[method, "bin", look] for look in LOOKS), fractions)
                     for method in methods}
    gains = {} if args.baseline is None else {
        method: {f"{split} {look}": _gain(paired(scores[args.baseline, split, look], scores[method, split, look]))
                 for split in SPLITS for look in LOOKS} for method in methods if method != args.baseline}
    rows = [[method, split, str(result["instances"]), f"{result['rendered']:.1f}", f"{result['path_traced']:.1f}",
             f"{result['drop']:+.1f} [{result['drop_interval'][0]:+.1f}, {result['drop_interval'][1]:+.1f}]"]
            for method, by_split in results.items() for split, result in by_split.items()]
    description = machine()
    markdown = "\n".join([
        f"# {args.name}: validation splits rendered and path traced"
        + (", crops from detector-like boxes" if args.detector_boxes else ""),
        "",
        "`" + " ".join(["python -m experiments.path_traced_gap", *(sys.argv[1:] if argv is None else argv)]) + "`",
        "",
        markdown_table(["method", "split", "instances", "rendered MSSD %", "path-traced MSSD %",
                        "paired drop (95 % interval)"], rows),
        "",
        *_gain_table(args.baseline, gains),
        "The bin's drop by visible fraction (paired, 95 % interval; instances in brackets):",
        "",
        markdown_table(["method", *by_visibility[next(iter(methods))]], [
            [method, *[f"{b['drop']:+.1f} [{b['drop_interval'][0]:+.1f}, {b['drop_interval'][1]:+.1f}] "
                       f"({b['instances']})" for b in bands.values()]] for method, bands in by_visibility.items()]),
        "",
        f"Path tracer: {json.dumps({k: round(v, 2) for k, v in seconds.items()})} seconds an image in this run "
        f"(empty: traced before). {machine_line(description)}",
    ])
    write_results(args.out, args.name, {"methods": methods, "detector_boxes": args.detector_boxes,
                                        "results": results, "bin_drop_by_visibility": by_visibility,
                                        "baseline": args.baseline,
                                        "gains": gains, "path_trace_seconds": seconds, "samples": args.samples,
                                        "images": args.images, "scenes": args.scenes}, markdown)
    print(markdown)
    return 0


if __name__ == "__main__":
    run_command("experiments.path_traced_gap", main)
