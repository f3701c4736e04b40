"""Checkpoints that survive a crash and load without unpickling code.

A checkpoint holds only tensors and plain Python values (dicts, lists,
numbers, strings), so ``torch.load(..., weights_only=True)`` reads it. It
is written to a temporary file and moved into place with ``os.replace``, so
a crash mid-write leaves the previous checkpoint intact.
"""

from __future__ import annotations

import os
import random
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import torch

from popcode_runtime.errors import PopcodeError

# Keys that may change when resuming: more epochs extend a run; the output folder may move.
RESUMABLE_CHANGES = {("train", "epochs"), ("train", "out_dir"), ("data", "num_workers")}


def save_atomic(state: dict[str, Any], path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    torch.save(state, temporary)
    os.replace(temporary, path)


def load(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True``; a file that needs pickled code is refused."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"checkpoint not found: {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises UnpicklingError, RuntimeError, EOFError...
        raise PopcodeError(f"cannot read checkpoint {path}: {str(error).splitlines()[0]}") from error


def rng_state() -> dict[str, Any]:
    """Every global random state, as tensors and plain values."""
    name, keys, position, has_gauss, cached = np.random.get_state()
    state = {
        "torch": torch.get_rng_state(),
        "numpy": [name, torch.from_numpy(keys.astype(np.int64)), position, has_gauss, cached],
        "python": random.getstate(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def restore_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    name, keys, position, has_gauss, cached = state["numpy"]
    np.random.set_state((name, keys.numpy().astype(np.uint32), position, has_gauss, cached))
    version, internal, gauss = state["python"]
    random.setstate((version, tuple(internal), gauss))
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def config_differences(saved: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """``section.key: saved -> current`` for every setting that differs and may not change on resume."""
    differences = []
    for section in sorted(set(saved) | set(current)):
        old, new = saved.get(section, {}), current.get(section, {})
        for key in sorted(set(old) | set(new)):
            if (section, key) not in RESUMABLE_CHANGES and old.get(key) != new.get(key):
                differences.append(f"{section}.{key}: {old.get(key)!r} -> {new.get(key)!r}")
    return differences


def git_revision() -> str:
    """The trainer's git commit (``+dirty`` with local changes), or ``unknown`` outside a checkout."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True,
                              check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, check=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return f"{head}+dirty" if dirty else head
