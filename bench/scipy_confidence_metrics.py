"""How far AUROC and the paired bootstrap interval move now that ``scipy.stats`` computes them (issue 66).

The hand-written versions are read from git at :data:`OLD_REVISION` and run beside the current ones on the same
fixed data: scores with many ties, and paired per-instance MSSD scores (steps of 0.1, as
``metrics.paired.instance_mssd_scores`` gives) of several sizes and seeds.

    python -m bench.scipy_confidence_metrics
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import types
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import scipy

from popcode_trainer.metrics.confidence import auroc
from popcode_trainer.metrics.paired import paired_difference
from tools.command import run_command
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

OLD_REVISION = "2758e7f"  # the last commit with the hand-written rank loop and bootstrap
ROOT = Path(__file__).resolve().parents[1]
SIZES = (20, 120, 1000, 5000)
SEEDS = range(5)


def old_module(name: str) -> types.ModuleType:
    """``popcode_trainer.metrics.<name>`` as it was at :data:`OLD_REVISION`."""
    source = subprocess.run(["git", "show", f"{OLD_REVISION}:trainer/popcode_trainer/metrics/{name}.py"], cwd=ROOT,
                            capture_output=True, text=True, check=True).stdout
    module = types.ModuleType(f"old_{name}")
    module.__package__ = "popcode_trainer.metrics"  # its relative imports resolve against today's package
    sys.modules[module.__name__] = module  # its dataclasses look their module up there
    exec(compile(source, f"{OLD_REVISION}:{name}.py", "exec"), module.__dict__)
    return module


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    old_auroc, old_paired = old_module("confidence").auroc, old_module("paired").paired_difference
    rows = []
    for size in SIZES:
        for seed in SEEDS:
            rng = np.random.default_rng(seed)
            score = np.round(rng.random(size), 1)
            correct = rng.random(size) < score
            first = rng.integers(0, 11, size) / 10
            second = np.clip(first + rng.integers(-2, 4, size) / 10, 0, 1)
            old, new = old_paired(first, second, seed=seed), paired_difference(first, second, seed=seed)
            rows.append({"instances": size, "seed": seed, "auroc_old": old_auroc(score, correct),
                         "auroc_new": auroc(score, correct), "interval_old": list(old.interval),
                         "interval_new": list(new.interval),
                         "interval_shift": float(np.abs(np.subtract(new.interval, old.interval)).max())})
    auroc_shift = max(abs(row["auroc_new"] - row["auroc_old"]) for row in rows)
    interval_shift = max(row["interval_shift"] for row in rows)
    lines = ["# AUROC and the paired bootstrap from scipy.stats against the hand-written ones", "",
             f"Same data, same seeds; the old code read from git at {OLD_REVISION}. Sizes {list(SIZES)} instances, "
             f"seeds {list(SEEDS)}: {len(rows)} cases.", "",
             "| instances | largest AUROC change | largest change of an interval end |", "|---:|---:|---:|"]
    for size in SIZES:
        chosen = [row for row in rows if row["instances"] == size]
        lines.append(f"| {size} | {max(abs(r['auroc_new'] - r['auroc_old']) for r in chosen):.1e} | "
                     f"{max(r['interval_shift'] for r in chosen):.1e} |")
    lines += ["", f"Largest change over all cases: AUROC {auroc_shift:.1e}, interval end {interval_shift:.1e} "
              "(float rounding only). `scipy.stats.bootstrap(paired=True, method=\"percentile\")` draws the "
              "instances from `np.random.default_rng(seed)` as the old loop did and takes the same percentiles, so "
              "the reported intervals do not move; `rankdata`'s average ranks are the old loop's.", "",
              machine_line(machine()) + f" scipy {scipy.__version__}.", "",
              "Command: `python -m bench.scipy_confidence_metrics`"]
    payload = {"scipy": scipy.__version__, "cases": rows, "largest_auroc_change": auroc_shift,
               "largest_interval_change": interval_shift}
    write_results(args.out, "scipy-confidence-metrics", payload, "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    run_command("bench.scipy_confidence_metrics", main)
