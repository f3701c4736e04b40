"""The paper's 1-D experiment (section IV-A, Table I): orientation of bars and arrows, every output representation.

    python -m bench.toy_orientation [--quick] [--repeats 10] [--epochs 30] [--jobs 2]
        [--no-augment] [--out DIR]

The images: :mod:`tools.toy_task` (ours; the paper shows examples only).

Network: the section IV-A ``ToyNet``. Training (ours; the paper gives none for
this experiment): Adam, learning rate 1e-3 decayed to 0 by a cosine over the
run (arrows, two repeats: refined error 3.7-4.1 -> 2.6-3.3 deg^2 against a
constant rate), batch 32, ``--epochs`` epochs (default 30), a fresh network and
a fresh 1000-image set split 800/200 per repeat. Each training batch is turned
by a random multiple of 90 deg and mirrored with probability 1/2, its angles
with it: the square image's eight symmetries move a shape exactly (no
resampling), and they took the arrows' refined error from 1.6-3.3 deg^2 (and a
reversed test arrow in 3 of 10 repeats) to under 1 deg^2; ``--no-augment``
trains on the 800 images as drawn. Targets: the scalar angle in radians (single
variable), a one-hot over 36 bins of 10 deg (MSE or cross entropy), a 36-neuron
population code (10 deg spacing, Gaussian tuning sigma 20 deg, MSE) and, for
bars, the code with both peaks (the angle and the angle + 180 deg, summed). The
population codes are decoded by argmax (the paper's) and by the runtime's
log-parabola refinement around the peak (``refine_angle``). Error: squared
angle difference [deg^2] on the 200 test images, bars modulo 180 deg; mean +-
sample std over repeats.
"""

from __future__ import annotations

import argparse
import multiprocessing
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812 (the usual torch alias)

from popcode_runtime.coding.population_code import CodeLayout
from popcode_runtime.coding.refine import refine_angle
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.train.network import ToyNet, ToyNetworkConfig
from tools.command import run_command
from tools.report import write_results
from tools.toy_task import PAPER, PERIOD_DEG, make_dataset, square_symmetry

TRAIN_COUNT, TEST_COUNT = 800, 200
LAYOUT = CodeLayout(n_axes=1, n_angles=36, sigma_deg=20.0)  # one circle of preferred angles, 10 deg apart
LEARNING_RATE = 1e-3
BATCH_SIZE = 32


def population_code(angles_rad: np.ndarray, peaks: int = 1) -> np.ndarray:
    """Targets ``(N, 36)``: Gaussian tuning around each angle, and around angle + 180 deg when ``peaks`` is 2."""
    code = np.zeros((len(angles_rad), LAYOUT.n_angles))
    for k in range(peaks):
        shifted = angles_rad[:, None] + k * np.pi - LAYOUT.angles_rad[None]
        distance = np.angle(np.exp(1j * shifted))  # wrapped to (-pi, pi]
        code += np.exp(-(distance**2) / (2.0 * LAYOUT.sigma_rad**2))
    return code


def decode_argmax(output: np.ndarray) -> np.ndarray:
    return LAYOUT.angles_rad[np.argmax(output, axis=1)]


def decode_refined(output: np.ndarray) -> np.ndarray:
    return np.array([refine_angle(LAYOUT, int(np.argmax(row)), row) for row in output])


@dataclass(frozen=True)
class Method:
    """One row group of Table I: output width, target, loss, and its decoders (name suffix -> decoder)."""

    name: str
    outputs: int
    target: Callable[[np.ndarray], np.ndarray]
    loss: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    decoders: dict[str, Callable[[np.ndarray], np.ndarray]]
    datasets: tuple[str, ...] = ("arrows", "bars")


def _one_hot(angles_rad: np.ndarray) -> np.ndarray:
    bins = np.round(angles_rad / (2.0 * np.pi / LAYOUT.n_angles)).astype(int) % LAYOUT.n_angles
    return np.eye(LAYOUT.n_angles)[bins]


def _cross_entropy(output: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    return F.cross_entropy(output, target.argmax(dim=1))


METHODS = (
    Method("Single Variable", 1, lambda a: a[:, None], F.mse_loss, {"": lambda out: out[:, 0]}),
    Method("One Hot (MSE)", 36, _one_hot, F.mse_loss, {"": decode_argmax}),
    Method("One Hot (Cross Entropy)", 36, _one_hot, _cross_entropy, {"": decode_argmax}),
    Method("Population Code", 36, population_code, F.mse_loss, {"": decode_argmax, " refined": decode_refined}),
    Method("Population Code (Sym)", 36, lambda a: population_code(a, peaks=2), F.mse_loss,
           {"": decode_argmax, " refined": decode_refined}, datasets=("bars",)),
)


def squared_error_deg2(predicted_rad: np.ndarray, true_rad: np.ndarray, period_deg: float) -> np.ndarray:
    """Squared angle difference [deg^2], the difference wrapped to the shape's symmetry period."""
    difference = np.degrees(predicted_rad - true_rad)
    wrapped = (difference + period_deg / 2) % period_deg - period_deg / 2
    return wrapped**2


def train_and_predict(method: Method, images: np.ndarray, angles: np.ndarray, train_count: int, epochs: int,
                      seed: int, augment: bool = True) -> np.ndarray:
    """Train a fresh ``ToyNet`` on the first ``train_count`` images; its raw outputs on the remaining ones."""
    torch.manual_seed(seed)
    model = ToyNet(ToyNetworkConfig(output_dim=method.outputs))
    optimizer = torch.optim.Adam(model.parameters(), lr=LEARNING_RATE)
    steps = epochs * -(-train_count // BATCH_SIZE)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    generator, symmetries = torch.Generator().manual_seed(seed), np.random.default_rng(seed)
    model.train()
    for _ in range(epochs):
        for batch in torch.randperm(train_count, generator=generator).split(BATCH_SIZE):
            rows = batch.numpy()
            x, y = images[rows], angles[rows]
            if augment:
                x, y = square_symmetry(x, y, int(symmetries.integers(4)), bool(symmetries.integers(2)))
            target = torch.from_numpy(method.target(y).astype(np.float32))
            loss = method.loss(model(torch.from_numpy(x)), target)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            schedule.step()
    model.eval()
    with torch.inference_mode():
        return model(torch.from_numpy(images[train_count:])).numpy()


def run_row_group(repeat: int, dataset: str, method_name: str, epochs: int, train_count: int,
                  test_count: int, augment: bool = True) -> dict[str, float]:
    """Mean squared error [deg^2] of each of one method's decoders in one repeat (its own data set and seed)."""
    method = next(m for m in METHODS if m.name == method_name)
    images, angles = make_dataset(dataset, train_count + test_count, np.random.default_rng([repeat, len(dataset)]))
    output = train_and_predict(method, images, angles, train_count, epochs, seed=repeat, augment=augment)
    return {method.name + suffix: float(squared_error_deg2(decode(output), angles[train_count:],
                                                           PERIOD_DEG[dataset]).mean())
            for suffix, decode in method.decoders.items()}


def run_repeats(repeats: int, epochs: int, train_count: int = TRAIN_COUNT, test_count: int = TEST_COUNT,
                methods: Sequence[Method] = METHODS, jobs: int = 1,
                augment: bool = True) -> dict[tuple[str, str], list[float]]:
    """Mean squared error [deg^2] of every (dataset, row) in every repeat, each on a new data set.

    With ``jobs`` > 1 the trainings run side by side in that many processes of
    one torch thread each. Each training is seeded by its repeat, so the
    results do not depend on ``jobs`` beyond floating-point summation order.
    """
    tasks = [(repeat, dataset, method.name) for repeat in range(repeats) for dataset in PERIOD_DEG
             for method in methods if dataset in method.datasets]
    group = partial(run_row_group, epochs=epochs, train_count=train_count, test_count=test_count, augment=augment)
    errors: dict[tuple[str, str], list[float]] = {}
    with ExitStack() as stack:
        mapper = map
        if jobs > 1:
            mapper = stack.enter_context(ProcessPoolExecutor(jobs, multiprocessing.get_context("spawn"),
                                                             initializer=torch.set_num_threads, initargs=(1,))).map
        for (repeat, dataset, _), rows in zip(tasks, mapper(group, *zip(*tasks, strict=True)), strict=True):
            for row, error in rows.items():
                errors.setdefault((dataset, row), []).append(error)
                print(f"repeat {repeat} {dataset} {row}: {error:.1f} deg^2", flush=True)
    return errors


def summarise(errors: dict[tuple[str, str], list[float]]) -> list[dict[str, Any]]:
    """One record per Table I row: mean and sample std over repeats, beside the paper's number."""
    return [{"dataset": dataset, "method": method, "mean": float(np.mean(runs)),
             "std": float(np.std(runs, ddof=1)) if len(runs) > 1 else 0.0, "runs": len(runs),
             "paper": PAPER.get((dataset, method))} for (dataset, method), runs in errors.items()]


def render_markdown(records: list[dict[str, Any]], epochs: int, augment: bool) -> str:
    """Table I layout: one row per method, ours and the paper's for arrows and bars."""
    methods = list(dict.fromkeys(r["method"] for r in records))
    cell = {(r["dataset"], r["method"]): f"{r['mean']:.1f} ± {r['std']:.1f}" for r in records}
    runs = max(r["runs"] for r in records)
    rows = [[m, cell.get(("arrows", m), "N/A"), PAPER.get(("arrows", m), ""), cell.get(("bars", m), "N/A"),
             PAPER.get(("bars", m), "")] for m in methods]
    header = ["method", "arrows (ours)", "arrows (paper)", "bars (ours)", "bars (paper)"]
    augmentation = "batches turned and mirrored by the square's symmetries" if augment else "no augmentation"
    return (f"Squared angle error [deg²], mean ± std over {runs} runs, {epochs} epochs each, {augmentation} "
            f"(bars modulo 180°).\n\n" + markdown_table(header, rows))


def _slug(text: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in text.lower()).strip("_")


def main(argv: Sequence[str] | None = None) -> list[dict[str, Any]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="1 repeat, 1 epoch, 64/32 images: a smoke run, not a result")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--epochs", type=int, default=30)
    parser.add_argument("--jobs", type=int, default=1,
                        help="trainings run side by side, one torch thread each (e.g. the number of cores)")
    parser.add_argument("--methods", nargs="+", metavar="NAME", choices=[m.name for m in METHODS],
                        help="train only these rows (default: all); results go to toy_orientation-<rows>.json/.md")
    parser.add_argument("--no-augment", dest="augment", action="store_false",
                        help="train on the images as drawn, without the square's symmetries; results go to "
                             "toy_orientation-no-augment.json/.md")
    parser.add_argument("--out", type=Path, default=Path("bench/results"), help="folder for toy_orientation.json/.md")
    args = parser.parse_args(argv)
    repeats, epochs, sizes = (1, 1, (64, 32)) if args.quick else (args.repeats, args.epochs, (TRAIN_COUNT, TEST_COUNT))
    methods = [m for m in METHODS if not args.methods or m.name in args.methods]
    name = ("toy_orientation" + ("-" + "-".join(_slug(m.name) for m in methods) if args.methods else "")
            + ("" if args.augment else "-no-augment"))
    records = summarise(run_repeats(repeats, epochs, *sizes, methods=methods, jobs=args.jobs, augment=args.augment))
    markdown = render_markdown(records, epochs, args.augment)
    settings = {"repeats": repeats, "epochs": epochs, "learning_rate": LEARNING_RATE, "schedule": "cosine",
                "batch_size": BATCH_SIZE, "train_test": sizes,
                "augmentation": "square symmetries per batch" if args.augment else "none"}
    write_results(args.out, name, {**settings, "records": records}, markdown)
    print(markdown)
    return records


if __name__ == "__main__":
    run_command("bench.toy_orientation", main)
