"""A kit whose detector gets another share of the budget (issue 63: the detector's share), for
``experiments.kit_hours`` to score beside kits of the shipped share (``popcode_trainer.kit.budget.DETECTOR_SHARE``).

    python -m experiments.kit_share --objects DIR --out KIT --hours 0.5 --detector-share 0.4

Everything else is what ``popcode-train kit --hours H`` makes of the budget: the same data sizes and recipe, the
pose models' epochs fitted to what the detector leaves. The demo pipeline runs in ``KIT/work`` (rerun to resume)
and the kit is laid out as ``kit`` lays it out, its ``kit.json`` naming the share.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from popcode_runtime.base.checks import number
from popcode_runtime.base.files import write_json_atomic
from popcode_trainer.demo.run import run_demo
from popcode_trainer.kit.budget import check_hours, kit_size
from popcode_trainer.kit.layout import write_kit
from popcode_trainer.kit.run import KIT_FILE, LATENCY_ITERATIONS, WORK_FOLDER, finished_demo
from tools.command import run_command
from tools.report import machine


def main(argv: Sequence[str] | None = None) -> None:
    """Make (or resume) the kit and lay it out."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=Path, required=True, help="a BOP models folder")
    parser.add_argument("--out", type=Path, required=True, help="the kit folder")
    parser.add_argument("--hours", type=float, required=True, help="the whole run's budget")
    parser.add_argument("--detector-share", type=float, required=True, help="of the budget, for the detector")
    args = parser.parse_args(argv)
    hours = check_hours(args.hours)
    share = number(args.detector_share, "--detector-share", 0.01, 0.9)
    size = replace(kit_size(hours), detector_seconds=3600.0 * hours * share)
    summary = finished_demo(args.out / WORK_FOLDER) or run_demo(
        f"kit {hours:g} h, detector {share:g}", args.out / WORK_FOLDER, size, latency_iterations=LATENCY_ITERATIONS,
        minutes=60.0 * hours, objects=args.objects)
    command = (f"python -m experiments.kit_share --objects {args.objects} --out {args.out} --hours {hours:g} "
               f"--detector-share {share:g}")
    record = {"objects": str(args.objects.resolve()), "hours": hours, "detector_share": share,
              "kit": write_kit(summary, args.out, command, machine())}
    write_json_atomic(args.out / KIT_FILE, record)
    print(f"kit written to {args.out}: card {record['kit']['card']}")


if __name__ == "__main__":
    run_command("experiments.kit_share", main)
