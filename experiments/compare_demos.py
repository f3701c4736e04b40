"""Two demo runs compared number by number: what a behaviour-preserving change must leave equal.

Compares every score, confidence and setting in ``summary.json``, every loss and
validation error in each model's ``metrics.csv``, every weight of every exported
ONNX model bit for bit, and its metadata (the training summary's run paths and
git revision aside); timings, machine and file names are left out, since they
differ between any two runs. Rendering is not bit-exact between processes (Mesa
may change a pixel by one grey level), so runs that are to be compared should
share their rendered splits: copy ``train/``, ``test/`` and ``test_cluttered/`` of
one run into both ``--out`` folders before running the demo (it resumes from them).

    python -m experiments.compare_demos runs/demo-before runs/demo-after
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import numpy_helper

from popcode_runtime.base.files import read_json
from popcode_trainer.demo.files import SUMMARY_FILE
from popcode_trainer.train.run_files import METRICS_FILE, read_metrics
from tools.command import run_command

# Keys of summary.json (at any depth) that measure time, name the machine or point at files: they differ between
# any two runs.
VARYING_KEYS = re.compile(r"second|_s$|latency|wall|machine|path|report|model_card|figures|samples|^models$|"
                          r"quantised_models")
LEARNING_COLUMNS = ("epoch", "train_loss", "val_loss", "val_error_mean_deg", "val_error_median_deg")
TRAINING_SUMMARY = "popcode.training"
RUN_SPECIFIC = ("dataset", "git_revision", "config")  # the run folder's paths and the revision


def json_differences(a: Any, b: Any, where: str) -> Iterator[str]:
    """Where two JSON values differ, keys that vary between any two runs aside."""
    if isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b)):
            if VARYING_KEYS.search(str(key)):
                continue
            if key not in a or key not in b:
                yield f"{where}.{key}: in one run only"
            else:
                yield from json_differences(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for index, (x, y) in enumerate(zip(a, b, strict=True)):
            yield from json_differences(x, y, f"{where}[{index}]")
    elif a != b:
        yield f"{where}: {a!r} != {b!r}"


def metrics_differences(a: Path, b: Path) -> Iterator[str]:
    """Every learning-curve value of every model of run ``a`` against run ``b``."""
    for path in sorted((a / "runs").glob(f"*/{METRICS_FILE}")):
        other = b / "runs" / path.parent.name / METRICS_FILE
        if not other.is_file():
            yield f"{path.parent.name}: no {METRICS_FILE} in {b}"
            continue
        x, y = read_metrics(path, LEARNING_COLUMNS), read_metrics(other, LEARNING_COLUMNS)
        for column in LEARNING_COLUMNS:
            if not np.array_equal(x[column], y[column]):
                yield f"{path.parent.name}/{METRICS_FILE} {column}: {x[column].tolist()} != {y[column].tolist()}"


def onnx_differences(a: Path, b: Path) -> Iterator[str]:
    """Every exported model's weights and metadata (but the training summary's run paths and revision)."""
    for path in sorted((a / "runs").glob("*/*.onnx")):
        other = b / "runs" / path.parent.name / path.name
        name = f"{path.parent.name}/{path.name}"
        if not other.is_file():
            yield f"{name}: missing in {b}"
            continue
        x, y = onnx.load(str(path)), onnx.load(str(other))
        weights_x = {t.name: numpy_helper.to_array(t) for t in x.graph.initializer}
        weights_y = {t.name: numpy_helper.to_array(t) for t in y.graph.initializer}
        if weights_x.keys() != weights_y.keys() or \
                not all(np.array_equal(weights_x[k], weights_y[k]) for k in weights_x):
            yield f"{name}: weights differ"
        props_x = {p.key: p.value for p in x.metadata_props}
        props_y = {p.key: p.value for p in y.metadata_props}
        for key in sorted(set(props_x) | set(props_y)):
            if key == TRAINING_SUMMARY:
                summary_x, summary_y = json.loads(props_x[key]), json.loads(props_y.get(key, "{}"))
                for field in RUN_SPECIFIC:
                    summary_x.pop(field, None), summary_y.pop(field, None)
                if summary_x != summary_y:
                    yield f"{name}: metadata {key} differs"
            elif props_x.get(key) != props_y.get(key):
                yield f"{name}: metadata {key} differs"


def compare(a: Path, b: Path) -> list[str]:
    """Every difference between the runs that is not a timing, a path or a revision."""
    summary_a, summary_b = read_json(a / SUMMARY_FILE), read_json(b / SUMMARY_FILE)
    return [*json_differences(summary_a, summary_b, SUMMARY_FILE), *metrics_differences(a, b),
            *onnx_differences(a, b)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", type=Path, help="a demo's --out folder")
    parser.add_argument("run_b", type=Path, help="the other demo's --out folder")
    args = parser.parse_args(argv)
    differences = compare(args.run_a, args.run_b)
    models = len(list((args.run_a / "runs").glob("*/*.onnx")))
    print(f"{len(differences)} differences ({models} ONNX models, their learning curves and {SUMMARY_FILE})")
    for difference in differences:
        print(difference)
    return 1 if differences else 0


if __name__ == "__main__":
    run_command("experiments.compare_demos", main)
