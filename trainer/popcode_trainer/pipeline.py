"""Render -> train -> export for the built-in objects: the steps the demo and the benchmarks share.

A ``PipelineSize`` fixes data, code, network and training budget, so every
representation trained with it sees the same inputs. Objects are pooled as the
paper pooled T-LESS objects: one model for the objects with a continuous
symmetry about the same axis (axis-only code), one for the others (full code).
Every step resumes: rendering skips finished images, training continues from
its last checkpoint and a finished export is kept.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.metadata import Representation
from popcode_runtime.symmetries import SymmetryClass, continuous_axis, symmetry_class

from .config import Config
from .data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from .export import export_checkpoint
from .run_files import LAST_CHECKPOINT, MODEL_FILE
from .train import train
from .training_data import build_training_data, validation_crops

ALL_REPRESENTATIONS = (Representation.POPULATION_CODE, Representation.SINGLE_VARIABLE,
                       Representation.ONE_HOT, Representation.MULTI_HYPOTHESIS)


@dataclass(frozen=True)
class PipelineSize:
    """Data, code, network and training budget shared by every representation of one run."""

    train_images_per_object: int
    test_images_per_object: int
    epochs: int
    n_axes: int
    n_angles: int
    network: dict[str, Any]
    batch_size: int = 32
    lr: float = 1e-3
    num_hypotheses: int = 20
    num_workers: int = 0
    representations: tuple[str, ...] = ALL_REPRESENTATIONS
    sigma_deg: float = 20.0
    seed: int = 0


# A network of a few per cent of the paper's width: trains in minutes on two CPU cores.
SMALL_NETWORK: dict[str, Any] = {"conv_channels": [16, 32, 32], "squeeze_channels": 8, "hidden": [256, 128, 128]}


def render_splits(size: PipelineSize, out_dir: Path, progress: bool = True) -> tuple[Path, Path]:
    """The training split and a separate test split (other seed), both with random object positions."""
    train_split = render_builtin_split(out_dir / "train", size.train_images_per_object, seed=size.seed,
                                       random_position=True, progress=progress)
    test_split = render_builtin_split(out_dir / "test", size.test_images_per_object, seed=size.seed + 1000,
                                      random_position=True, progress=progress)
    return train_split, test_split


def object_groups(models_info: Mapping[int, Mapping[str, Any]]) -> list[list[int]]:
    """Objects that can share one model: continuous symmetries about one axis together, the rest together."""
    by_axis: dict[tuple[float, ...], list[int]] = {}
    full = []
    for obj_id in sorted(models_info):
        if symmetry_class(models_info[obj_id]) is SymmetryClass.CONTINUOUS:
            axis = continuous_axis(models_info[obj_id])
            axis = axis if axis[np.argmax(np.abs(axis))] > 0 else -axis  # an axis and its reverse are one
            by_axis.setdefault(tuple(np.round(axis, 6)), []).append(obj_id)
        else:
            full.append(obj_id)
    return [*by_axis.values(), *([full] if full else [])]


def training_config(size: PipelineSize, representation: str, obj_ids: Sequence[int], split: Path,
                    out_dir: Path) -> Config:
    """The training config of one model of the run."""
    return Config.from_dict({
        "data": {"splits": [str(split)], "models_dir": str(split / BUILTIN_MODELS_FOLDER), "obj_ids": list(obj_ids),
                 "num_workers": size.num_workers},
        "code": {"n_axes": size.n_axes, "n_angles": size.n_angles, "sigma_deg": size.sigma_deg},
        "network": size.network,
        "train": {"representation": representation, "epochs": size.epochs, "batch_size": size.batch_size,
                  "lr": size.lr, "num_hypotheses": size.num_hypotheses, "seed": size.seed, "out_dir": str(out_dir),
                  "device": "auto"},
    })


def run_dir(out_dir: Path, representation: str, obj_ids: Sequence[int]) -> Path:
    """Where one model's checkpoints, metrics and ONNX files live."""
    return out_dir / "runs" / f"{representation}_{'-'.join(map(str, obj_ids))}"


def train_and_export(size: PipelineSize, representation: str, obj_ids: Sequence[int], split: Path, out_dir: Path,
                     quantisations: tuple[str, ...] = ()) -> tuple[Path, float]:
    """Train (resuming an interrupted run) and export one model; returns the float ONNX path and the seconds.

    Quantised variants are written beside it as ``model.<kind>.onnx``.
    """
    folder = run_dir(out_dir, representation, obj_ids)
    onnx_path = folder / MODEL_FILE
    config = training_config(size, representation, obj_ids, split, folder)
    started = time.perf_counter()
    quantised = [folder / f"{onnx_path.stem}.{kind}.onnx" for kind in quantisations]
    if not onnx_path.exists() or not all(path.exists() for path in quantised):
        data = build_training_data(config)
        train(config, data.representation, data.train_set, data.val_set,
              resume=(folder / LAST_CHECKPOINT).exists(), val_instances=data.val_instances)
        crops, obj_ids = validation_crops(config)
        export_checkpoint(folder / LAST_CHECKPOINT, onnx_path, crops, quantisations, obj_ids=obj_ids)
    return onnx_path, time.perf_counter() - started
