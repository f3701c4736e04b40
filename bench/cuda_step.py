"""The training step alone on a CUDA GPU: does a GPU run wait on its step or on its crops?

    python -m bench.cuda_step [--batch-sizes 32 128] [--steps 300] [--compiled] [--out bench/results]
        [--name cuda-step]

The quick recipe's network and loss (642 x 36 code for built-in parts 3-6, MSE + cross entropy), random crops
and targets already on the GPU, so nothing but the step is timed:

- ``loop's step``: as ``train.loop`` runs it on CUDA: ``channels_last`` when the widths allow, fp16 autocast
  with a gradient scaler, fused Adam, the learning rate set and the loss read back (a synchronisation) every step;
- ``no read-back``: the same without reading the loss back, so the CPU queues steps ahead of the GPU;
- ``compiled`` (with ``--compiled``): the loop's step with ``train.compile = "on"``, whose forward and backward
  ``train.fast_path`` compiles with CUDA graphs; its first step's seconds (the compile) in the note;
- ``CUDA graph``: one step (bf16 autocast, no scaler, Adam with ``capturable``) captured once and replayed —
  what a captured step could reach, with the launches of a step's hundreds of small kernels gone.

Each at every ``--batch-sizes``, after warm-up steps; crops/s and ms a step. The real loop's crops/s of a run
come from its ``metrics.csv`` (``bench/results/shipped-models.md`` compares the two). Needs a CUDA device.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import torch

from popcode_runtime.base.errors import first_line
from popcode_trainer.demo.parts import builtin_parts
from popcode_trainer.demo.steps import small_config
from popcode_trainer.eval.reporting.markdown import markdown_table
from popcode_trainer.train.fast_path import GuardedForward, StepPath, adam, channels_last_is_safe
from popcode_trainer.train.loop import network_config
from popcode_trainer.train.network import build_network
from popcode_trainer.train.representations import build_representation
from tools.command import run_command
from tools.report import machine, machine_line, write_results

OBJECTS = (3, 4, 5, 6)
WARM_UP_STEPS = 20


def _model_and_loss(device: torch.device) -> tuple[torch.nn.Module, Callable, int, bool]:
    """The quick recipe's network for parts 3-6 on ``device``, its loss, code width and whether it runs
    ``channels_last``."""
    config = small_config(epochs=1, n_axes=642, n_angles=36)
    objects = {obj_id: builtin_parts().models_info[obj_id] for obj_id in OBJECTS}
    code, train = config.code, config.train
    representation = build_representation("population_code", objects, code.n_axes, code.n_angles, code.sigma_deg,
                                          sigma_from_symmetries=code.sigma_from_symmetries, loss=train.loss)
    network = network_config(config, representation)
    layout = channels_last_is_safe(network.conv_channels)
    model = build_network(network).to(device)
    if layout:
        model = model.to(memory_format=torch.channels_last)
    return model, representation.loss, representation.output_dim, layout


def _timed(step: Callable[[], None], steps: int) -> float:
    for _ in range(WARM_UP_STEPS):
        step()
    torch.cuda.synchronize()
    started = time.perf_counter()
    for _ in range(steps):
        step()
    torch.cuda.synchronize()
    return time.perf_counter() - started


def measure(batch_size: int, steps: int, device: torch.device, compiled: bool = False) -> list[dict[str, Any]]:
    """The steps' rates at one batch size."""
    torch._dynamo.reset()  # each batch size compiles afresh, as a run would (not a dynamic-batch recompile)
    rows = []
    model, loss_of, width, layout = _model_and_loss(device)
    crop = small_config(epochs=1, n_axes=642, n_angles=36).data.crop_size
    images = torch.rand(batch_size, 1, crop, crop, device=device)
    if layout:
        images = images.contiguous(memory_format=torch.channels_last)
    targets = torch.rand(batch_size, width, device=device)
    lr = 1e-3

    variants = [("loop's step", True, False), ("no read-back", False, False)]
    variants += [("compiled", True, True)] if compiled else []
    for name, read_back, compile_step in variants:
        optimizer = adam(model.parameters(), lr, device)
        scaler = torch.amp.GradScaler("cuda")
        forward = GuardedForward(model, StepPath(layout, "fp32", compile_step, "bench"))

        def step(optimizer: torch.optim.Optimizer = optimizer, scaler: torch.amp.GradScaler = scaler,
                 read_back: bool = read_back, forward: GuardedForward = forward) -> None:
            for group in optimizer.param_groups:
                group["lr"] = lr
            with torch.autocast("cuda", dtype=torch.float16):
                output = forward(images)
            loss = loss_of(output.float(), targets, 0.5)
            optimizer.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.step(optimizer)
            scaler.update()
            if read_back:
                float(loss.detach())

        started = time.perf_counter()
        step()
        first_s = time.perf_counter() - started
        row = _row(name, batch_size, steps, _timed(step, steps))
        rows.append({**row, "note": f"first step {first_s:.1f} s; {forward.path.describe()}" if compile_step
                     else ""})

    optimizer = torch.optim.Adam(model.parameters(), lr=lr, capturable=True)

    def plain_step() -> None:
        optimizer.zero_grad(set_to_none=False)
        with torch.autocast("cuda", dtype=torch.bfloat16, cache_enabled=False):  # no cached casts across a capture
            output = model(images)
        loss_of(output.float(), targets, 0.5).backward()
        optimizer.step()

    try:
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):  # warm-up on a side stream, as capture requires
            for _ in range(3):
                plain_step()
        torch.cuda.current_stream().wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            plain_step()
        rows.append(_row("CUDA graph", batch_size, steps, _timed(graph.replay, steps)))
    except RuntimeError as error:  # a loss that reads a value back cannot be captured: say so, keep the rest
        rows.append({**_row("CUDA graph", batch_size, steps, float("nan")), "note": first_line(error)})
    return rows


def _row(name: str, batch_size: int, steps: int, seconds: float) -> dict[str, Any]:
    return {"step": name, "batch": batch_size, "crops_per_s": batch_size * steps / seconds,
            "ms_per_step": 1000 * seconds / steps, "note": ""}


def to_markdown(payload: dict[str, Any]) -> str:
    rows = [[row["step"], row["batch"], f"{row['crops_per_s']:.0f}", f"{row['ms_per_step']:.2f}", row["note"]]
            for row in payload["rows"]]
    return "\n".join([
        "# The training step alone on a CUDA GPU", "",
        f"{machine_line(payload['machine'])} GPU: {payload['gpu']}. Command: `python -m bench.cuda_step "
        f"{payload['arguments']}`. The quick recipe's network and loss, 642 x 36 code (parts 3-6), random crops "
        "and targets on the GPU.", "",
        markdown_table(["step", "batch", "crops/s", "ms / step", "note"], rows),
    ])


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch-sizes", nargs="+", type=int, default=[32, 128])
    parser.add_argument("--steps", type=int, default=300, help="timed steps per row (after warm-up steps)")
    parser.add_argument("--compiled", action="store_true",
                        help="also time the step compiled with CUDA graphs (train.compile = on; compiles first)")
    parser.add_argument("--out", type=Path, default=Path("bench/results"))
    parser.add_argument("--name", default="cuda-step")
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        parser.error("no CUDA device: this bench times the step on a GPU")
    if min(args.batch_sizes) < 2 or args.steps < 1:
        parser.error("--batch-sizes must be at least 2 (batch norm) and --steps at least 1")
    device = torch.device("cuda")
    rows = [row for size in args.batch_sizes for row in measure(size, args.steps, device, args.compiled)]
    arguments = " ".join(sys.argv[1:] if argv is None else argv)
    payload = {"arguments": arguments, "gpu": torch.cuda.get_device_name(), "rows": rows, "machine": machine()}
    write_results(args.out, args.name, payload, to_markdown(payload))
    print(to_markdown(payload), flush=True)
    return payload


if __name__ == "__main__":
    run_command("bench.cuda_step", main)
