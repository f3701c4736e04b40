"""Pretraining: a network trained on many generated parts, whose trunk is saved as a start for other parts' models
(``popcode-train pretrain``; issue 53).

Steps, each resumed where an interrupted run left it: generate the parts (:mod:`..data.generated_parts`; the kinds
the full code takes: n-fold, none and look-alike), check them as ``demo --objects`` checks a user's parts, render
single-part images and bin scenes of them, train one population-code model on all of them with the demo's network
and recipe (its epochs fitted to ``minutes`` after the first, or given), and write the start
(:func:`..train.pretrained.write_start`) with its card: what it saw, how long, which commit.
"""

from __future__ import annotations

import time
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import torch

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json, write_json_atomic
from popcode_runtime.inference.benchmark import machine_description
from popcode_runtime.model.metadata import Representation

from ..data.generated_parts import generate_parts, kinds_of, write_generated_models
from ..data.near_symmetry import LookAlikeWarning
from ..export.model_io import load_trained_model
from ..train import checkpoint
from ..train.config import Config
from ..train.loop import train
from ..train.network import NetworkConfig
from ..train.pretrained import NONE, write_start
from ..train.run_files import LAST_CHECKPOINT, read_metrics
from ..train.training_data import TrainingData, build_training_data, read_training_split
from . import epoch_budget
from .parts import Parts, load_parts
from .steps import (
    IMAGES_PER_SCENE,
    SMALL_NETWORK,
    TRAIN_SCENES_SEED_OFFSET,
    PipelineSize,
    _render_processes,
    in_processes,
    scene_split_of,
    small_config,
    training_config,
)

PRETRAIN_KINDS = ("discrete", "none", "look_alike")  # the kinds one full-code model takes
PARTS_FOLDER, SPLIT_FOLDER, RUN_FOLDER, START_NAME = "parts", "train", "run", "pretrained-start.pt"
SCENE_SHARE = 0.25  # as the demo's quick size (bench/results/scene-mix-quick.md)


@dataclass(frozen=True)
class PretrainSize:
    """What a pretraining sees: how many parts, images and scenes, its code and network, and its budget."""

    parts: int = 200
    images_per_part: int = 300
    scenes: int = 300
    n_axes: int = 642
    n_angles: int = 36
    network: NetworkConfig = SMALL_NETWORK  # the demo's: its models take the start
    epochs: int | None = None  # None: fitted to minutes
    minutes: float = 60.0
    seed: int = 0

    def pipeline(self, epochs: int) -> PipelineSize:
        config = small_config(epochs, self.n_axes, self.n_angles, network=self.network, init=NONE)
        return PipelineSize(self.images_per_part, 0, config, (Representation.POPULATION_CODE,),
                            train_scenes=self.scenes, scene_share=SCENE_SHARE if self.scenes else 0.0)


def prepare_parts(size: PretrainSize, out_dir: Path, progress: bool = True) -> Parts:
    """The generated parts in ``out_dir/parts`` (written once), checked as a user's parts are."""
    folder = out_dir / PARTS_FOLDER
    if not (folder / "models_info.json").is_file():
        write_generated_models(generate_parts(size.parts, size.seed, PRETRAIN_KINDS), folder)
    elif len(kinds_of(folder)) != size.parts:
        raise PopcodeError(f"{out_dir} was started with {len(kinds_of(folder))} parts, not {size.parts}: use another "
                           "--out, or the same --parts")
    if progress:
        print(f"checking {size.parts} generated parts (mesh, size, symmetries)", flush=True)
    return load_parts(folder)


@dataclass(frozen=True)
class _WithoutLookAlikeWarnings:
    """A render step whose near-symmetry warnings are silenced (in a render process too): the look-alike parts look
    symmetric by design, and hundreds of parts would print hundreds of them."""

    render: Callable[..., Path]

    def __call__(self, *args: Any, **kwargs: Any) -> Path:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", LookAlikeWarning)
            return self.render(*args, **kwargs)


def render(size: PretrainSize, parts: Parts, out_dir: Path, progress: bool = True) -> Path:
    """The training split (and its scenes) of the generated parts; returns the split."""
    split = in_processes(_WithoutLookAlikeWarnings(partial(parts.render_split, out_dir / SPLIT_FOLDER,
                                                           size.images_per_part, size.seed)),
                         progress, _render_processes(size.images_per_part * size.parts))
    if size.scenes:
        in_processes(_WithoutLookAlikeWarnings(partial(parts.render_scenes, scene_split_of(split), size.scenes,
                                                       size.seed + TRAIN_SCENES_SEED_OFFSET)),
                     progress, _render_processes(size.scenes * IMAGES_PER_SCENE))
    return split


def train_model(size: PretrainSize, parts: Parts, split: Path, out_dir: Path) -> Config:
    """Train the one model of every generated part (resuming), its epochs fitted to ``size.minutes`` after the
    first unless given; returns its config."""
    folder = out_dir / RUN_FOLDER
    fit_path = folder / epoch_budget.FIT_FILE
    epochs = size.epochs
    if epochs is None and fit_path.is_file():
        epochs = int(read_json(fit_path)["epochs"])
    if epochs is None:  # train the first epoch of a run of unknown length (its rate does not depend on it) and time it
        config = training_config(size.pipeline(1), Representation.POPULATION_CODE, parts.obj_ids, split, folder)
        if not (folder / LAST_CHECKPOINT).is_file():
            data = _training_data(config)
            train(config, data.representation, data.train_set, data.val_set, val_instances=data.val_instances,
                  stop_after_epoch=1)
        seconds = float(read_metrics(folder, ("seconds",))["seconds"][0])
        epochs = epoch_budget.fitted_epochs(seconds, 60.0 * size.minutes - seconds, (2, 1000))
        write_json_atomic(fit_path, {"epochs": epochs, "first_epoch_seconds": seconds, "minutes": size.minutes})
        print(f"{epochs} epochs: one takes {seconds:.0f} s here and the budget is {size.minutes:g} min", flush=True)
    config = training_config(size.pipeline(epochs), Representation.POPULATION_CODE, parts.obj_ids, split, folder)
    data = _training_data(config)
    train(config, data.representation, data.train_set, data.val_set, val_instances=data.val_instances,
          resume=(folder / LAST_CHECKPOINT).is_file())
    return config


def _training_data(config: Config) -> TrainingData:
    """The crops to pretrain on, refused in one line when they fill no batch: the training loop's advice would name
    ``train.batch_size``, which pretrain does not take."""
    split = read_training_split(config)  # counted before the crops are cached: no progress bar before the refusal
    if len(split.train) < config.train.batch_size:
        raise PopcodeError(f"the generated parts make {len(split.train)} training crops, fewer than one batch "
                           f"({config.train.batch_size}): raise --images, --parts or --scenes")
    return build_training_data(config, split=split)


def card(size: PretrainSize, parts: Parts, config: Config, started: float) -> dict:
    """What the start saw and how it was made: the parts by kind, data, epochs, validation error, commit, machine."""
    folder = Path(config.train.out_dir)
    metrics = read_metrics(folder, ("seconds", "val_error_median_deg"))
    kinds = Counter(kinds_of(parts.source)) if parts.source is not None else Counter()
    return {"parts": len(parts.obj_ids), "kinds": dict(Counter(kinds.values())), "parts_seed": size.seed,
            "images_per_part": size.images_per_part, "scenes": size.scenes, "scene_share": SCENE_SHARE,
            "code": [size.n_axes, size.n_angles], "epochs": config.train.epochs,
            "training_seconds": round(float(metrics["seconds"].sum()), 1),
            "wall_minutes_this_call": round((time.perf_counter() - started) / 60.0, 1),
            "val_error_median_deg": round(float(metrics["val_error_median_deg"][-1]), 2),
            "commit": checkpoint.git_revision(), "date": time.strftime("%Y-%m-%d"),
            "machine": {**machine_description(), "torch": str(torch.__version__)}}


def pretrain(size: PretrainSize, out_dir: Path, progress: bool = True) -> Path:
    """Every step (each resumed); returns the start file ``out_dir/pretrained-start.pt``."""
    started = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():  # the look-alike parts look symmetric by design: no warning for each
        warnings.simplefilter("ignore", LookAlikeWarning)
        parts = prepare_parts(size, out_dir, progress)
        split = render(size, parts, out_dir, progress)
        config = train_model(size, parts, split, out_dir)
    trained = load_trained_model(Path(config.train.out_dir) / LAST_CHECKPOINT).network
    return write_start(trained, trained.config, out_dir / START_NAME, card(size, parts, config, started))
