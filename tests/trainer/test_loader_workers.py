"""The demo gives a CUDA run loader workers (the GPU's step outpaces one core's crops) and a CPU run none."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from popcode_trainer.demo import steps
from popcode_trainer.demo.steps import loader_workers, small_config


@pytest.mark.parametrize(("cuda", "device", "cores", "set_workers", "expected"), [
    (False, "auto", 16, 0, 0),   # no GPU: the loader shares the cores with training
    (True, "cpu", 16, 0, 0),     # a GPU the run does not use
    (True, "auto", 16, 0, steps.GPU_LOADER_WORKERS),
    (True, "cuda", 4, 0, 2),     # two cores kept for the training process and the system
    (True, "auto", 2, 0, 0),
    (True, "auto", 16, 3, 3),    # workers the size sets are kept
])
def test_loader_workers(monkeypatch: pytest.MonkeyPatch, cuda: bool, device: str, cores: int, set_workers: int,
                        expected: int) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    monkeypatch.setattr(steps.os, "cpu_count", lambda: cores)
    config = small_config(epochs=2, n_axes=42, n_angles=12)
    config = replace(config, data=replace(config.data, num_workers=set_workers),
                     train=replace(config.train, device=device))
    assert loader_workers(config) == expected
