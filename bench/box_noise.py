"""The IoU with the true box that each box-noise preset gives (``popcode_trainer.data.box_noise``).

    python -m bench.box_noise [--draws 20000] [--out bench/results]

A unit box and its noisy versions, no image border (clipping only lowers the IoU of border-cut parts).
Results: ``bench/results/box-noise.{json,md}``.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from popcode_trainer.data.box_noise import BOX_NOISE_PRESETS, iou_statistics
from popcode_trainer.eval.reporting.markdown import markdown_table
from tools.command import run_command
from tools.report import machine, machine_line, write_results


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=20000, help="noisy boxes per preset")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    args = parser.parse_args(argv)
    rows = {name: {**vars(noise), **iou_statistics(noise, args.draws)} for name, noise in BOX_NOISE_PRESETS.items()}
    description = machine()
    table = markdown_table(
        ["preset", "log-scale sd", "shift sd (share of side)", "log-aspect sd", "IoU mean", "5 %", "median", "95 %"],
        [[name, f"{r['log_scale']:g}", f"{r['shift']:g}", f"{r['log_aspect']:g}", f"{r['mean']:.3f}",
          f"{r['p05']:.3f}", f"{r['median']:.3f}", f"{r['p95']:.3f}"] for name, r in rows.items()])
    markdown = "\n\n".join([
        "# Box-noise presets: IoU with the true box",
        f"`python -m bench.box_noise --draws {args.draws}`: {args.draws} noisy versions of one box per preset "
        "(scale, centre shift and aspect drawn from normals, no image border). `evaluate --box-noise`, "
        "`popcode-train detections` and `data.box_noise` (training crops) use these presets.",
        machine_line(description), table])
    write_results(args.out, "box-noise", {"draws": args.draws, "presets": rows}, markdown)
    return rows


if __name__ == "__main__":
    run_command("bench.box_noise", lambda: 0 if main() else 1)
