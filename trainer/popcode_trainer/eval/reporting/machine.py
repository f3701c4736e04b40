"""What a measurement or a kit ran on: the runtime's machine description with torch's version and threads, the
load (other work skews timings) and the device training used."""

from __future__ import annotations

import os
from typing import Any

import torch

from popcode_runtime.inference.benchmark import machine_description


def machine() -> dict[str, Any]:
    """The machine record that results files and kit cards name."""
    device = f"CUDA ({torch.cuda.get_device_name()})" if torch.cuda.is_available() else "the CPU"
    return {**machine_description(), "torch": torch.__version__, "torch_threads": torch.get_num_threads(),
            "load_average_1m": os.getloadavg()[0], "device": device}
