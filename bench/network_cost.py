"""Size, MACs and training throughput of the paper-size network on this machine.

    python -m bench.network_cost [--steps 5] [--batch 64]

Throughput is optimiser steps only (forward, MSE on the code, backward, Adam)
on random crops, so it is the network's ceiling; data loading is not counted.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import torch

from popcode_trainer.train.network import NetworkConfig, PopcodeNet, count_macs, count_parameters
from tools.command import run_command


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()

    config = NetworkConfig()
    model = PopcodeNet(config)
    macs = count_macs(model, config.input_size)
    model.to(args.device).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-4)
    image = torch.rand(args.batch, 1, config.input_size, config.input_size, device=args.device)
    target = torch.rand(args.batch, config.output_dim, device=args.device)
    for step in range(args.warmup + args.steps):
        if step == args.warmup:
            if args.device.startswith("cuda"):
                torch.cuda.synchronize()
            started = time.perf_counter()
        loss = torch.nn.functional.mse_loss(model(image), target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    if args.device.startswith("cuda"):
        torch.cuda.synchronize()
    seconds = time.perf_counter() - started
    print(json.dumps({
        "config": {k: v for k, v in vars(config).items()},
        "parameters": count_parameters(model),
        "output_layer_parameters": sum(p.numel() for p in model.head.parameters()),
        "macs_per_crop": macs,
        "device": args.device,
        "torch_threads": torch.get_num_threads(),
        "cpu": platform.processor() or platform.machine(),
        "batch": args.batch,
        "train_samples_per_s": args.steps * args.batch / seconds,
    }, indent=1))


if __name__ == "__main__":
    run_command("bench.network_cost", main)
