"""Training throughput per trunk: where a step's time goes (data preparation, forward + backward, optimizer).

    python -m bench.training [--quick] [--out DIR] [--networks small paper] [--threads 1 2] [--workers 0 2]
                             [--paths eager-nchw-fp32 eager-cl-fp32 ...] [--loop-epochs 3] [--images 2000]

Renders a small split of the built-in parts into a temporary folder and builds
the population-code training data exactly as ``popcode-train train`` does
(``pipeline.small_config``: 642 x 36 code, batch 32, the paper's augmentation).
For each network and torch thread count it times, in crops per second:

- ``data``: batches from the DataLoader alone (read PNG, crop, augment, build
  the target), with each number of DataLoader workers;
- ``forward_backward``: network, loss and backward on one fixed batch;
- ``optimizer``: Adam's step alone;
- ``step``: loader -> forward -> loss -> backward -> step as the loop runs them, per
  worker count, on the path ``popcode-train train`` chooses on this machine
  (``train.fast_path``: layout, precision, compiled or not), which is what a
  training run gets;
- ``path: ...``: the whole step (forward, loss, backward, Adam) on a fixed
  batch for each path: eager or compiled, NCHW or ``channels_last``, fp32 or
  bf16 autocast (``--paths``); the compile's seconds are in ``first_s``;
- ``loop``: ``popcode-train train``'s own loop (``train.loop.train``: loader,
  step, progress bar, learning-rate schedule) over ``--loop-epochs`` epochs of
  the split with the worker count of the quick recipe, one call per epoch (each
  resumes the last); after each epoch but the first, the plain eager NCHW fp32
  step is timed again on the fixed batch, in a process of its own that keeps
  the C library's allocator defaults. Its crops/s are the median over those
  epochs (without a compiled step's compile, which each call repeats and one run
  pays once), and the note the median of each epoch's multiple of the plain step
  timed beside it (the issue's measure of the training speed-up).

Numbers, not assertions; results in ``bench/results/training.{json,md}``.
"""

from __future__ import annotations

import argparse
import copy
import multiprocessing
import resource
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader

from popcode_trainer.demo.steps import PipelineSize, render_splits, small_config, training_config
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.train import allocator, checkpoint
from popcode_trainer.train.config import Config
from popcode_trainer.train.fast_path import GuardedForward, StepPath, adam, autocast, choose_path, to_layout
from popcode_trainer.train.loop import network_config, train
from popcode_trainer.train.network import NetworkConfig, build_network
from popcode_trainer.train.run_files import LAST_CHECKPOINT
from popcode_trainer.train.training_data import TrainingData, build_training_data
from tools.command import run_command
from tools.recipes import NETWORKS
from tools.report import machine, machine_line, write_results

PATHS = {  # name -> (channels_last, precision, compiled)
    "eager-nchw-fp32": StepPath(False, "fp32", False, "bench"),  # what training did before fast_path
    "eager-cl-fp32": StepPath(True, "fp32", False, "bench"),
    "eager-nchw-bf16": StepPath(False, "bf16", False, "bench"),  # chosen for narrow networks on a native-bf16 CPU
    "eager-cl-bf16": StepPath(True, "bf16", False, "bench"),
    "compiled-cl-fp32": StepPath(True, "fp32", True, "bench"),
    "compiled-cl-bf16": StepPath(True, "bf16", True, "bench"),
}
BATCH = 32
IMAGES_PER_OBJECT = 2000  # as the quick demo: 4 x 2000 x 0.9 = 7200 training crops, loop epochs of 225 batches


def _rate(crops: int, seconds: float) -> float:
    return crops / seconds if seconds > 0 else float("nan")


def _timed_batches(loader: DataLoader, batches: int, work: Callable[[dict[str, Any]], None]) -> float:
    """Seconds for ``batches`` batches after one warm-up batch (worker start-up, first allocations)."""
    iterator = iter(loader)
    work(next(iterator))
    started = time.perf_counter()
    for _ in range(batches):
        work(next(iterator))
    return time.perf_counter() - started


def path_step_rate(base: torch.nn.Module, path: StepPath, batch: dict[str, Any], loss_of: Callable, lr: float,
                   batches: int) -> tuple[float, float, StepPath, dict[str, float]]:
    """Crops/s of the whole step on one fixed batch on ``path`` (a copy of ``base``), the first step's seconds (a
    compile's included), the path that ran (a failed compile falls back to eager) and the kernel's share of a
    timed step: its minor page faults and system CPU milliseconds (the work ``train.allocator`` saves)."""
    model = copy.deepcopy(base)
    if path.channels_last:
        model = model.to(memory_format=torch.channels_last)
    optimizer = adam(model.parameters(), lr, torch.device("cpu"))
    forward = GuardedForward(model, path)
    images = to_layout(batch["image"], path)
    cpu = torch.device("cpu")

    def step() -> None:
        with autocast(forward.path, cpu, cuda_amp=False):
            output = forward(images)
        loss = loss_of(output.float(), batch["target"], 0.5)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    started = time.perf_counter()
    step()
    first_s = time.perf_counter() - started
    step()  # a compiled backward may finish compiling on its second call
    usage, started = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for _ in range(batches):
        step()
    seconds, after = time.perf_counter() - started, resource.getrusage(resource.RUSAGE_SELF)
    kernel = {"page_faults_per_step": (after.ru_minflt - usage.ru_minflt) / batches,
              "kernel_ms_per_step": 1000 * (after.ru_stime - usage.ru_stime) / batches}
    return _rate(batches * BATCH, seconds), first_s, forward.path, kernel


def _plain_step_rate(net_config: NetworkConfig, threads: int, batch: dict[str, Any], loss_of: Callable, lr: float,
                     batches: int) -> float:
    """Crops/s of the plain eager NCHW fp32 step of a new network of ``net_config`` (run in a process of its own)."""
    torch.set_num_threads(threads)
    model = build_network(net_config).train()
    return path_step_rate(model, PATHS["eager-nchw-fp32"], batch, loss_of, lr, batches)[0]


def loop_beside_plain(config: Config, data: TrainingData, epochs: int, out_dir: Path,
                      plain_rate: Callable[[], float]) -> tuple[list[float], list[float], str]:
    """Crops/s of each epoch of the training loop after the first, each with the plain step's crops/s measured right
    after it, and the path the loop took. The host's speed drifts by tens of per cent within minutes, so only a
    pair taken together compares like with like."""
    config = replace(config, train=replace(config.train, epochs=epochs, out_dir=str(out_dir)))
    loop_rates, plain_rates = [], []
    for epoch in range(1, epochs + 1):  # one call per epoch: the run resumes, as after a kill
        history = train(config, data.representation, data.train_set, resume=epoch > 1, stop_after_epoch=epoch)
        if epoch > 1:  # the first pays the first allocations
            row = history[-1]  # a compiled step compiles again in each call: one run compiles once
            loop_rates.append(row.samples_per_s * row.seconds / (row.seconds - row.compile_seconds))
            plain_rates.append(plain_rate())
    path = StepPath(**checkpoint.load(out_dir / LAST_CHECKPOINT)["step_path"])
    return loop_rates, plain_rates, path.describe()


def measure(network_name: str, threads: int, workers: Sequence[int], batches: int, split: Path,
            out_dir: Path, paths: Sequence[str] = tuple(PATHS), loop_epochs: int = 3,
            images_per_object: int = IMAGES_PER_OBJECT) -> list[dict[str, Any]]:
    """One network at one torch thread count: the rows of every part and worker count."""
    torch.set_num_threads(threads)
    size = PipelineSize(images_per_object, 0, small_config(epochs=1, n_axes=642, n_angles=36,
                                                           network=NETWORKS[network_name]))
    config = training_config(size, "population_code", [3, 4, 5, 6], split, out_dir)
    data = build_training_data(config)
    model = build_network(network_config(config, data.representation)).train()
    optimizer = adam(model.parameters(), config.train.lr, torch.device("cpu"))
    loss_of = data.representation.loss
    rows = []

    def row(part: str, seconds: float, crops: int, workers_used: int | None = None, **extra: Any) -> None:
        rows.append({"network": network_name, "threads": threads, "part": part, "workers": workers_used,
                     "crops_per_s": _rate(crops, seconds), "ms_per_batch": 1000 * seconds / (crops / BATCH),
                     "memory_kept": allocator.freed_memory_kept(), **extra})

    def loader(num_workers: int) -> DataLoader:
        return DataLoader(data.train_set, batch_size=BATCH, shuffle=True, drop_last=True, num_workers=num_workers,
                          generator=torch.Generator().manual_seed(0))

    needed = (batches + 1) * BATCH
    if len(data.train_set) < needed:
        raise SystemExit(f"the split has {len(data.train_set)} training crops, {needed} are needed")
    for count in workers:
        row("data", _timed_batches(loader(count), batches, lambda _batch: None), batches * BATCH, count)
    fixed = next(iter(loader(0)))

    def forward_backward(batch: dict[str, Any]) -> torch.Tensor:
        optimizer.zero_grad(set_to_none=True)
        loss = loss_of(model(batch["image"]).float(), batch["target"], 0.5)
        loss.backward()
        return loss

    forward_backward(fixed)  # warm-up
    started = time.perf_counter()
    for _ in range(batches):
        forward_backward(fixed)
    row("forward_backward", time.perf_counter() - started, batches * BATCH)
    started = time.perf_counter()
    for _ in range(batches):
        optimizer.step()
    row("optimizer", time.perf_counter() - started, batches * BATCH)
    def path_row(name: str) -> None:
        rate, first_s, ran, kernel = path_step_rate(model, PATHS[name], fixed, loss_of, config.train.lr, batches)
        row(f"path: {name}", BATCH * batches / rate, BATCH * batches, first_s=first_s,
            fell_back=PATHS[name].compiled and not ran.compiled, **kernel)

    for name in paths:
        path_row(name)
    chosen = choose_path(config.train.precision, config.train.compile, torch.device("cpu"),
                         config.train.epochs * (len(data.train_set) // BATCH),
                         conv_widths=NETWORKS[network_name].conv_channels)
    # From here on as training runs: freed memory kept for the next step (train.allocator). The rows above ran
    # with the C library's defaults unless an earlier network's measurement had already set it (memory_kept).
    if not allocator.freed_memory_kept() and allocator.keep_freed_memory():
        name = next((name for name, path in PATHS.items() if (path.channels_last, path.precision, path.compiled)
                     == (chosen.channels_last, chosen.precision, chosen.compiled)), None)
        if name is not None:
            path_row(name)
    model = model.to(memory_format=torch.channels_last) if chosen.channels_last else model
    forward = GuardedForward(model, chosen)
    for count in workers:
        def step(batch: dict[str, Any]) -> None:
            with autocast(forward.path, torch.device("cpu"), cuda_amp=False):
                output = forward(to_layout(batch["image"], forward.path))
            loss = loss_of(output.float(), batch["target"], 0.5)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
        row("step", _timed_batches(loader(count), batches, step), batches * BATCH, count,
            path=forward.path.describe())
    if loop_epochs > 1:
        # The plain step runs in a process of its own, with the C library's allocator defaults, as a plain PyTorch
        # training process has them (this one keeps freed memory since the rows above).
        with multiprocessing.get_context("spawn").Pool(1) as plain_process:
            plain_arguments = (network_config(config, data.representation), threads, fixed, loss_of,
                               config.train.lr, batches)

            def plain_rate() -> float:
                return plain_process.apply(_plain_step_rate, plain_arguments)

            loop_rates, plain_rates, path = loop_beside_plain(config, data, loop_epochs,
                                                              out_dir / f"loop-{network_name}-{threads}", plain_rate)
        ratios = [loop / plain for loop, plain in zip(loop_rates, plain_rates, strict=True)]
        row("loop", BATCH / float(np.median(loop_rates)), BATCH, config.data.num_workers, path=path,
            vs_plain_eager=float(np.median(ratios)), epoch_crops_per_s=loop_rates, plain_crops_per_s=plain_rates)
    return rows


def _note(row: dict[str, Any]) -> str:
    kept = "; freed memory kept" if row.get("memory_kept") else ""
    if row.get("vs_plain_eager") is not None:
        return f"{row['vs_plain_eager']:.2f}x the plain eager NCHW fp32 step; {row['path']}{kept}"
    if "first_s" in row:
        return (f"first step {row['first_s']:.1f} s" + (" (compile failed: ran eager)" if row["fell_back"] else "")
                + f"; {row['page_faults_per_step']:.0f} page faults, {row['kernel_ms_per_step']:.1f} ms in the "
                "kernel a step" + kept)
    return row.get("path", "") + kept


def to_markdown(payload: dict[str, Any]) -> str:
    description = payload["machine"]
    header = ["network", "threads", "part", "workers", "crops/s", "ms / batch of 32", "note"]
    rows = [(r["network"], r["threads"], r["part"], "–" if r["workers"] is None else r["workers"],
             f"{r['crops_per_s']:.1f}", f"{r['ms_per_batch']:.1f}", _note(r)) for r in payload["rows"]]
    return "\n\n".join([
        "# Training throughput",
        f"{machine_line(description)} Command: `python -m bench.training {payload['arguments']}`. "
        f"Population code 642 x 36, batch {BATCH}, "
        "the paper's augmentation on rendered 128 px images of built-in parts 3-6.",
        "`data`: DataLoader batches alone; `forward_backward`: network + loss + backward on a fixed batch; "
        "`optimizer`: Adam's step; `step`: loader and step as the training loop runs them, on the path training "
        "chooses here (note); `loop`: `popcode-train train`'s own loop, the median of its epochs after the first, "
        "and the median of their multiples of the plain eager NCHW fp32 step timed again after each, in a process of "
        "its own with the C library's defaults; "
        "`path: ...`: the whole step on a fixed batch, eager or compiled, NCHW or channels_last (cl), fp32 or bf16 "
        "autocast; the first step's seconds include a compile. \"freed memory kept\": measured after the trainer "
        "kept freed memory for the next step (`train/allocator.py`), as training runs; the other rows with the C "
        "library's defaults, as a plain PyTorch step runs.",
        markdown_table(header, rows),
    ])


def run(networks: Sequence[str], threads: Sequence[int], workers: Sequence[int], batches: int, out_dir: Path,
        arguments: str, paths: Sequence[str] = tuple(PATHS), loop_epochs: int = 3,
        images_per_object: int = IMAGES_PER_OBJECT) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as folder:
        size = PipelineSize(images_per_object, 1, small_config(epochs=1, n_axes=642, n_angles=36))
        split, _ = render_splits(size, Path(folder), progress=False)
        rows = [row for name in networks for count in threads
                for row in measure(name, count, workers, batches, split, Path(folder) / "run", paths, loop_epochs,
                                   images_per_object)]
    payload = {"arguments": arguments, "batch": BATCH, "rows": rows}
    payload["machine"] = machine()
    write_results(out_dir, "training", payload, to_markdown(payload))
    return payload


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two batches per measurement: a smoke run")
    parser.add_argument("--out", type=Path, default=Path("bench/results"), help="folder for training.json/.md")
    parser.add_argument("--networks", nargs="+", choices=list(NETWORKS),
                        default=["small", "small-paper-trunk", "paper"])
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2], help="torch intra-op threads to try")
    parser.add_argument("--workers", nargs="+", type=int, default=[0, 2], help="DataLoader worker counts to try")
    parser.add_argument("--batches", type=int, default=6, help="timed batches per measurement (after a warm-up)")
    parser.add_argument("--paths", nargs="*", choices=list(PATHS), default=list(PATHS),
                        help="step paths to time on a fixed batch (compiled ones compile first: 15-60 s each)")
    parser.add_argument("--loop-epochs", type=int, default=3,
                        help="epochs of the training loop itself to time (the first is not counted; 0 or 1: none)")
    parser.add_argument("--images", type=int, default=IMAGES_PER_OBJECT,
                        help=f"images rendered per part (default {IMAGES_PER_OBJECT}; fewer make shorter loop epochs)")
    args = parser.parse_args(argv)
    if min(args.threads) < 1 or min(args.workers) < 0 or args.batches < 1 or args.loop_epochs < 0 or args.images < 1:
        parser.error("--threads, --batches and --images must be at least 1, --workers and --loop-epochs at least 0")
    batches = 2 if args.quick else args.batches
    loop_epochs = min(args.loop_epochs, 2) if args.quick else args.loop_epochs
    arguments = " ".join(sys.argv[1:] if argv is None else argv)
    return run(args.networks, args.threads, args.workers, batches, args.out, arguments, args.paths, loop_epochs,
               args.images)


if __name__ == "__main__":
    run_command("bench.training", main)
