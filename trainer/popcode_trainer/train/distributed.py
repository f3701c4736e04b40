"""One process or many under ``torchrun``: the same training code runs in both.

``torchrun`` sets ``WORLD_SIZE``/``RANK``/``LOCAL_RANK``; with more than one
process we join a process group (NCCL when every rank has a GPU, else gloo).
Only rank 0 writes files or prints progress.
"""

from __future__ import annotations

import gc
import os
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from popcode_runtime.base.errors import PopcodeError


@dataclass(frozen=True)
class Context:
    """Where this process runs: its rank among ``world_size`` and its device."""

    rank: int
    world_size: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def _pick_device(requested: str, local_rank: int) -> torch.device:
    if requested == "cuda" and not torch.cuda.is_available():
        raise PopcodeError("train.device = 'cuda' but PyTorch sees no CUDA device; use 'auto' or 'cpu'")
    if requested in ("cuda", "auto") and torch.cuda.is_available():
        return torch.device("cuda", local_rank % torch.cuda.device_count())
    return torch.device("cpu")


def launched_rank() -> int:
    """This process's rank as ``torchrun`` launched it (0 alone), known before the process group is joined."""
    return int(os.environ.get("RANK", "0"))


def launched_world_size() -> int:
    """How many ranks ``torchrun`` launched (1 alone), known before the process group is joined."""
    return int(os.environ.get("WORLD_SIZE", "1"))


def setup(requested_device: str) -> Context:
    """Join the ``torchrun`` process group if there is one; pick this rank's device."""
    world_size = launched_world_size()
    rank = launched_rank()
    device = _pick_device(requested_device, int(os.environ.get("LOCAL_RANK", "0")))
    if world_size > 1 and not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group(backend="nccl" if device.type == "cuda" else "gloo")
    return Context(rank=rank, world_size=world_size, device=device)


def teardown(context: Context, finished: bool = False) -> None:
    """Leave the process group. A rank sometimes aborted at exit after a finished run ("terminate called
    without an active exception", SIGABRT; gloo on CPU, under load): the DDP wrapper sits in reference
    cycles, so its reducer and the gloo work it holds outlived the group until the interpreter's final
    garbage collection, which cannot run them down safely. So the cycles are collected first, while the
    group is alive; then a ``finished`` run waits for every rank (a failed one does not: its peers may
    never arrive) and destroys the group."""
    if context.distributed and dist.is_initialized():
        gc.collect()
        if finished:
            dist.barrier()
        dist.destroy_process_group()


def sum_over_ranks(values: list[float], context: Context) -> list[float]:
    """Element-wise sum of a few numbers over all ranks (identity for one process)."""
    if not context.distributed:
        return values
    tensor = torch.tensor(values, dtype=torch.float64, device=context.device)
    dist.all_reduce(tensor)
    return tensor.tolist()


def gather_lists(items: list[Any], context: Context) -> list[Any]:
    """Concatenate a small list from every rank, in rank order."""
    if not context.distributed:
        return items
    gathered: list[list[Any]] = [[] for _ in range(context.world_size)]
    dist.all_gather_object(gathered, items)
    return [item for part in gathered for item in part]
