"""Checkpoints that survive a crash and load without unpickling code.

A checkpoint holds only tensors and plain Python values (dicts, lists,
numbers, strings), so ``torch.load(..., weights_only=True)`` reads it. It
is written with the runtime's one atomic write (a temporary file, synced, renamed), so
a crash or a power cut mid-write leaves the previous checkpoint intact.
"""

from __future__ import annotations

import dataclasses
import pickle
import random
import subprocess
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from popcode_runtime.base.errors import PopcodeError, first_line
from popcode_runtime.base.files import atomic_path, remove_stale_temporaries
from popcode_runtime.model.metadata import ModelMetadata

from ..data.hull import with_hull_points

# Keys that may change when resuming: more epochs extend a run; the output folder may move; compiling only changes
# how the step runs.
RESUMABLE_CHANGES = {("train", "epochs"), ("train", "out_dir"), ("data", "num_workers"), ("data", "cache_dir"),
                     ("train", "compile")}
# What every checkpoint of ``popcode-train train`` holds (train/loop.py's state dict); export and evaluate need them.
TRAINED_KEYS = frozenset({"network", "model", "metadata", "config", "epoch", "best_val_error_deg"})


def save_atomic(state: dict[str, Any], path: Path) -> None:
    """``state`` at ``path``, synced before and after its rename; what a crashed save left beside it goes first."""
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    with atomic_path(path) as temporary:
        torch.save(state, temporary)


def load(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint with ``weights_only=True``; a file that needs pickled code is refused."""
    path = Path(path)
    if not path.is_file():
        raise PopcodeError(f"checkpoint not found: {path}")
    _check_archive(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as error:
        if "Unsupported global" not in str(error):  # not a pickle of plain data at all
            raise PopcodeError(f"cannot read checkpoint {path}: not a torch checkpoint file") from error
        # weights_only refused a class it would have to import: torch explains for a page, one line is enough
        raise PopcodeError(f"{path} is not a trusted popcode checkpoint: it needs pickled code to load, which "
                           "popcode never runs") from error
    except Exception as error:  # RuntimeError, EOFError, zipfile errors...: not a torch file at all
        raise PopcodeError(f"cannot read checkpoint {path}: {first_line(error)}") from error
    if not isinstance(state, dict):
        raise PopcodeError(f"{path} is not a popcode checkpoint: it holds a {type(state).__name__}, not a dict")
    return state


def _check_archive(path: Path) -> None:
    """Refuse a checkpoint whose bytes changed after it was written. torch.save stores each part's CRC-32 in its zip
    archive, but torch.load does not check them (PyTorch builds its zip reader without), so a start or checkpoint
    with flipped bytes would load and be trained from; zipfile's test reads every part against its CRC (a few ms a
    MB). A file that is no zip archive is left to torch.load, which reads the legacy format or names the problem."""
    try:
        with zipfile.ZipFile(path) as archive:
            damaged = archive.testzip()
    except zipfile.BadZipFile:
        return
    except Exception as error:  # a header that names an unknown compression, a truncated part...
        raise PopcodeError(f"cannot read checkpoint {path}: {first_line(error)}") from error
    if damaged is not None:
        raise PopcodeError(f"{path} is damaged: its part {damaged} does not match the checksum it was written with "
                           "(the file changed on disk or in transfer); copy it again, or write it anew")


def load_trained(path: str | Path) -> dict[str, Any]:
    """A checkpoint written by ``popcode-train train``, recognised by its keys before any is used."""
    state = load(path)
    missing = sorted(TRAINED_KEYS - set(state))
    if missing:
        raise PopcodeError(f"{path} is not a popcode training checkpoint: it lacks {missing}")
    wrong = sorted(key for key in ("network", "model", "metadata", "config") if not isinstance(state[key], dict))
    if wrong:
        raise PopcodeError(f"{path} is not a popcode training checkpoint: {wrong} are not dicts")
    return state


def metadata_props(metadata: ModelMetadata, input_size: int, models_dir: str | Path | None) -> dict[str, str]:
    """The metadata a checkpoint stores: the representation's, at the crop size the network was trained on (the
    runtime crops at that size, not the default), with each object's ``hull_points_mm`` from its mesh in
    ``models_dir``, computed once per run so that export needs neither the meshes nor the time.

    Without a models folder (data sets built in code) the objects are kept as they are; export then looks for
    meshes as it does for a checkpoint written before hull points were stored.
    """
    objects = with_hull_points(metadata.objects, models_dir) if models_dir else metadata.objects
    return dataclasses.replace(metadata, input_size=input_size, objects=objects).to_props()


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


def config_differences(saved: dict[str, Any], current: dict[str, Any],
                       defaults: dict[str, Any] | None = None) -> list[str]:
    """``section.key: saved -> current`` for every setting that differs and may not change on resume.

    A setting added since the checkpoint was written (absent from ``saved``) counts as its value in ``defaults``
    (the config's defaults), so a newer trainer resumes an older run that its defaults describe.
    """
    differences = []
    for section in sorted(set(saved) | set(current)):
        old, new = saved.get(section, {}), current.get(section, {})
        old = {**(defaults or {}).get(section, {}), **old}
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
