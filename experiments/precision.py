"""Does bf16 training lose accuracy? The quick recipe in fp32 and in bf16 autocast at equal epochs, per seed.

    python -m experiments.precision [--config trainer/configs/quick.toml] [--set KEY=VALUE ...] [--epochs 12]
        [--images 800] [--seeds 0 1] [--obj-ids 3 4 5 6] [--work DIR] [--name precision]

Each (precision, seed) trains one model with ``experiments.budget_curve.curve`` (the built-in parts' training split,
seed 0, and its validation split, seed 2000) and scores its last checkpoint: MSSD on the validation split and
the median error on the images the run held out of training. The exported model is fp32 whatever the training
precision, so both are scored the same way.

On a CPU without native bf16 the bf16 run is emulated (several times slower than fp32) but rounds the same
way: autocast casts the convolutions' and matmuls' inputs to bf16 and their products are summed in fp32, as
AMX and AVX512-BF16 do; so the accuracy measured here is the accuracy a bf16 run gets on a CPU that has it,
and only the speed differs (``bench/results/training.md``). ``--work`` keeps splits and runs: an interrupted
comparison resumes. Results: ``bench/results/precision.{json,md}`` (``--name``).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch.nn import functional as F  # noqa: N812 (the usual torch alias)

from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.train.config import load_config
from tools.command import run_command
from tools.experiment import VALIDATION_SEED
from tools.paths import RESULTS
from tools.report import machine, machine_line, write_results

from .budget_curve import curve

PRECISIONS = ("fp32", "bf16")
BF16_OUTPUT_ROUNDING = 2.0**-8  # relative: the largest error of rounding an fp32 value to bf16's 8-bit mantissa


def autocast_rounding() -> dict[str, float]:
    """The largest relative error of a bf16-autocast matmul (8192 products a sum) and convolution on this CPU against
    fp32 sums of the same bf16-rounded inputs: about :data:`BF16_OUTPUT_ROUNDING` where the products are summed in
    fp32 (as AMX does), several times more where they were summed in bf16."""
    generator = torch.Generator().manual_seed(0)
    a, b = torch.rand(64, 8192, generator=generator), torch.rand(8192, 64, generator=generator)
    x, w = torch.rand(4, 64, 32, 32, generator=generator), torch.rand(64, 64, 5, 5, generator=generator)
    exact_mm = a.bfloat16().float() @ b.bfloat16().float()
    exact_conv = F.conv2d(x.bfloat16().float(), w.bfloat16().float(), padding=2)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mm, conv = a @ b, F.conv2d(x, w, padding=2)
    return {"matmul": float(((mm.float() - exact_mm).abs() / exact_mm).max()),
            "conv": float(((conv.float() - exact_conv).abs() / exact_conv).max())}


def compare(config: Path, overrides: Sequence[str], epochs: int, images: int, seeds: Sequence[int],
            obj_ids: Sequence[int], work: Path) -> list[dict[str, Any]]:
    rows = []
    for seed in seeds:
        for precision in PRECISIONS:
            base = load_config(config, [*overrides, f'train.precision="{precision}"', f"train.seed={seed}"])
            point = curve(base, [epochs], images, obj_ids, work, f"precision-{precision}-seed{seed}")[-1]
            rows.append({"precision": precision, "seed": seed, **point})
    return rows


def to_markdown(rows: Sequence[dict[str, Any]], rounding: dict[str, float], arguments: str,
                description: dict[str, Any]) -> str:
    obj_ids = list(rows[0]["mssd_per_object"])
    header = ["precision", "seed", "epochs", "crop-updates", "training min", "crops/s", "MSSD %",
              "median error ° (held-out)", *(f"obj {obj}" for obj in obj_ids)]
    table = [[r["precision"], str(r["seed"]), str(r["epochs"]), f"{r['crop_updates']:,}",
              f"{r['training_s'] / 60:.1f}", f"{r['crop_updates'] / r['training_s']:.0f}", f"{100 * r['mssd']:.1f}",
              f"{r['held_out_median_deg']:.1f}", *(f"{100 * r['mssd_per_object'][obj]:.1f}" for obj in obj_ids)]
             for r in rows]
    means = []
    for precision in PRECISIONS:
        chosen = [r for r in rows if r["precision"] == precision]
        means.append(f"{precision} {100 * sum(r['mssd'] for r in chosen) / len(chosen):.1f} % MSSD, "
                     f"{sum(r['held_out_median_deg'] for r in chosen) / len(chosen):.1f}° median")
    return "\n".join([
        "# bf16 training against fp32: accuracy at equal epochs", "",
        f"`python -m experiments.precision {arguments}`. MSSD (BOP19 recall, rotation only, GT translation) on the "
        f"validation split (seed {VALIDATION_SEED}) and the median rotation error on the images each run held out of "
        "its training split; the exported models are fp32. On a CPU without native bf16 the bf16 run is emulated: "
        "the same roundings (bf16 inputs, fp32 sums) at a fraction of the speed, so compare accuracy here and speed "
        "in `training.md`.", "",
        machine_line(description), "", markdown_table(header, table), "",
        f"Mean over seeds: {'; '.join(means)}.", "",
        f"Autocast's rounding on this CPU: the largest relative error of a bf16 matmul of 8192 products a sum "
        f"{rounding['matmul']:.4f}, of a 5x5 convolution over 64 channels {rounding['conv']:.4f}, against fp32 sums "
        f"of the same bf16 inputs (bf16's own output rounding: {BF16_OUTPUT_ROUNDING:.4f}).",
    ])


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=Path("trainer/configs/quick.toml"))
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one setting of the config (repeatable; not train.precision or train.seed)")
    parser.add_argument("--epochs", type=int, default=12, help="epochs of every run")
    parser.add_argument("--images", type=int, default=800, help="training images per part")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1], help="training seeds, one run per precision")
    parser.add_argument("--obj-ids", nargs="+", type=int, default=[3, 4, 5, 6], help="built-in parts (one model)")
    parser.add_argument("--work", type=Path, default=Path("runs/precision"), help="splits and runs (resumable)")
    parser.add_argument("--name", default="precision", help="results file stem (bench/results/NAME.{json,md})")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.epochs < 1 or args.images < 1:
        parser.error("--epochs and --images must be at least 1")
    if any(o.split("=", 1)[0].strip() in ("train.precision", "train.seed") for o in args.overrides):
        parser.error("train.precision and train.seed are what this compares: use --seeds")
    rows = compare(args.config, args.overrides, args.epochs, args.images, args.seeds, args.obj_ids, args.work)
    arguments = " ".join(sys.argv[1:] if argv is None else argv)
    rounding = autocast_rounding()
    payload = {"arguments": arguments, "config": str(args.config), "overrides": args.overrides, "rows": rows,
               "autocast_rounding": rounding}
    write_results(args.out, args.name, payload, to_markdown(rows, rounding, arguments, machine()))
    return rows


if __name__ == "__main__":
    run_command("experiments.precision", lambda: 0 if main() else 1)
