"""Render -> train -> export: the steps the demo and the benchmarks share (the built-in parts by default, or a
user's, :mod:`popcode_trainer.demo.parts`).

A ``PipelineSize`` fixes data, code, network and training budget, so every
representation trained with it sees the same inputs. Objects are pooled as the
paper pooled T-LESS objects: one model for the objects with a continuous
symmetry about the same axis (axis-only code), one for the others (full code);
a group may train on its own grid (:mod:`popcode_trainer.demo.group_codes`).
Every step resumes: rendering skips finished images, training continues from
its last checkpoint and a finished export is kept.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.population_code import PAPER_SIGMA_DEG
from popcode_runtime.geometry.symmetries import SymmetryClass, continuous_axis, symmetry_class
from popcode_runtime.model.metadata import Representation, RotationFrame

from ..data.path_trace import PathTraceSettings
from ..data.path_traced_split import path_trace_split
from ..data.render import BUILTIN_MODELS_FOLDER
from ..detection.config import DetectorConfig
from ..export.confidence_fit import calibrate_checkpoint
from ..export.model_io import load_trained_model
from ..export.onnx_export import export_trained
from ..train import checkpoint
from ..train.config import CodeConfig, Config, DataConfig, TrainConfig
from ..train.loop import train
from ..train.network import NetworkConfig
from ..train.pretrained import NONE
from ..train.run_files import CROP_CACHE_FOLDER, LAST_CHECKPOINT, MODEL_FILE
from ..train.training_data import build_training_data, read_training_split, validation_crops
from .epoch_budget import first_epoch_compile_seconds, first_epoch_seconds
from .parts import Parts, builtin_parts

RENDER_PROCESSES = 8  # at most this many shards of a split rendered side by side (the progress bar shows the first)
GPU_LOADER_WORKERS = 8  # 14 trained no faster on a 16-core H100 machine (bench/results/shipped-models.md)
MIN_IMAGES_PER_PROCESS_START = 400  # a process starts in seconds (spawn, imports): smaller splits render in this one
IMAGES_PER_SCENE = 25  # a 720 x 540 scene costs about as much as this many 128 x 128 single-part images
TEST_SEED_OFFSET = 1000  # the clean test split renders with seed + 1000
TRAIN_SCENES_SEED_OFFSET = 3000  # the clean test split renders with seed + 1000, the cluttered one seed + 2000
# Single parts path traced for training: seed + 7000 (4000 to 6002 are the experiments' validation and test seeds),
# their materials and lights drawn with path-trace seed 1 (the validation splits' are drawn with 0).
TRACED_TRAIN_SEED_OFFSET, TRACED_TRAIN_LOOK_SEED = 7000, 1
ALL_REPRESENTATIONS = (Representation.POPULATION_CODE, Representation.SINGLE_VARIABLE,
                       Representation.ONE_HOT, Representation.MULTI_HYPOTHESIS)


@dataclass(frozen=True)
class PipelineSize:
    """Data and training budget shared by every representation of one run.

    ``config`` holds the code, network and training settings every model of
    the run starts from (its data splits, objects, representation and output
    folder are filled in per model by :func:`training_config`); the rest is
    what a ``Config`` does not describe: how many images (and cluttered test
    scenes) to render and which representations to train.
    """

    train_images_per_object: int
    test_images_per_object: int
    config: Config
    representations: tuple[str, ...] = ALL_REPRESENTATIONS
    cluttered_test_scenes: int = 0  # a second, cluttered test split (parts in a bin, occlusion, sensor effects)
    train_scenes: int = 0  # cluttered training scenes rendered beside the single-part images
    scene_share: float = 0.0  # the share of scene crops in an epoch when there are training scenes
    detector_seconds: float = 0.0  # training time of a detector on the training scenes (0: none)
    detector: DetectorConfig = field(default_factory=DetectorConfig)  # with detector_seconds: its recipe
    path_traced_images: int = 0  # per object: the first test images path traced and scored too (0: none)
    traced_train_images: int = 0  # per object: single-part training images path traced (0: none) ...
    traced_share: float = 0.0  # ... and their share of every epoch's crops (bench/results/path-traced.md)

    def __post_init__(self) -> None:
        if not 0.0 <= self.scene_share < 1.0 or (self.scene_share > 0) != (self.train_scenes > 0):
            raise PopcodeError(f"scene_share must lie in [0, 1) and be positive exactly when there are training "
                               f"scenes; got {self.scene_share} with {self.train_scenes} scenes")
        if self.traced_train_images < 0 or (self.traced_share > 0) != (self.traced_train_images > 0) or \
                not 0.0 <= self.traced_share < 1.0 - self.scene_share:
            raise PopcodeError(f"traced_share must lie in [0, 1 - scene_share) and be positive exactly when there are "
                               f"path-traced training images; got {self.traced_share} with "
                               f"{self.traced_train_images} images and scene_share {self.scene_share}")
        if not 0 <= self.path_traced_images <= self.test_images_per_object:
            raise PopcodeError(f"path_traced_images must lie in [0, test_images_per_object], got "
                               f"{self.path_traced_images}")
        if self.detector_seconds < 0 or (self.detector_seconds > 0 and not self.train_scenes):
            raise PopcodeError(f"a detector trains on the training scenes: detector_seconds {self.detector_seconds} "
                               f"needs train_scenes > 0, got {self.train_scenes}")

    def with_epochs(self, epochs: int) -> PipelineSize:
        """The same run trained for ``epochs`` epochs."""
        return replace(self, config=replace(self.config, train=replace(self.config.train, epochs=epochs)))

    def with_init(self, init: str) -> PipelineSize:
        """The same run, its models starting from ``init`` (``train.init``: "auto", "none" or a start file); "none"
        starts its detector from random weights too (a pose model's start file is no detector's)."""
        detector = replace(self.detector, init=NONE) if init == NONE else self.detector
        return replace(self, config=replace(self.config, train=replace(self.config.train, init=init)),
                       detector=detector)


# A network of a few per cent of the paper's width that trains in minutes on two CPU cores: residual
# blocks beat the paper's layout shrunk to this width, at fewer MACs (bench/results/recipe.md); an MLP of
# 512 / 256 / 256 (was 256 / 128 / 128) scores higher on clean and cluttered validation splits of the built-in
# parts and, more, of parts no choice was tuned on, at about the same step time (bench/results/head-width.md).
SMALL_NETWORK = NetworkConfig(conv_channels=(16, 32, 64), squeeze_channels=8, hidden=(512, 256, 256),
                              trunk="residual")


def small_config(epochs: int, n_axes: int, n_angles: int, network: NetworkConfig = SMALL_NETWORK,
                 sigma_deg: float = PAPER_SIGMA_DEG, box_noise: tuple[str, float] = ("none", 1.0),
                 **train: Any) -> Config:
    """Settings for a CPU budget: the paper's recipe with batch 32, lr 1e-3 annealed over the last fifth of the
    run, no data-loader workers and the population code trained with MSE plus cross entropy (it learns parts
    without symmetry, which MSE alone does not at this budget, and keeps MSE's accuracy on symmetric ones:
    bench/results/recipe.md); sigma is narrowed where a part's symmetric peaks would merge
    (:mod:`popcode_trainer.train.code_sigma`). Rotations are allocentric, as the crop shows them: a crop cannot
    tell how far off the optical axis its part lay, which egocentric targets need (bench/results/rotation-frame.md).

    ``box_noise``: ``data.box_noise`` and ``data.box_noise_p`` (training crops from detector-like boxes).
    ``train`` overrides further :class:`~popcode_trainer.train.config.TrainConfig` fields.
    """
    train_config = TrainConfig(**{"epochs": epochs, "batch_size": 32, "lr": 1e-3, "schedule": "anneal",
                                  "loss": "mse+cross_entropy",
                                  "rotation_frame": RotationFrame.ALLOCENTRIC, **train})
    code = CodeConfig(n_axes, n_angles, sigma_deg, sigma_from_symmetries=True)
    data = DataConfig(num_workers=0, box_noise=box_noise[0], box_noise_p=box_noise[1])
    return Config(data=data, code=code, network=network, train=train_config)


def scene_split_of(train_split: Path) -> Path:
    """Where the training scenes of a run lie, beside its single-part training split."""
    return train_split.with_name(f"{train_split.name}_scenes")


def traced_split_of(train_split: Path) -> Path:
    """Where the path-traced training images of a run lie, beside its single-part training split."""
    return train_split.with_name(f"{train_split.name}_path_traced")


def render_splits(size: PipelineSize, out_dir: Path, progress: bool = True,
                  parts: Parts | None = None) -> tuple[Path, Path]:
    """The training split (and its scenes, :func:`scene_split_of`) and a separate test split (other seed), all
    with random object positions, of ``parts`` (default: the built-in ones); each split holds its models."""
    parts = parts or builtin_parts()
    seed = size.config.train.seed
    images = size.train_images_per_object * len(parts.obj_ids)
    train_split = in_processes(partial(parts.render_split, out_dir / "train", size.train_images_per_object, seed),
                               progress, _render_processes(images))
    if size.train_scenes:
        in_processes(partial(parts.render_scenes, scene_split_of(train_split), size.train_scenes,
                             seed + TRAIN_SCENES_SEED_OFFSET), progress,
                     _render_processes(size.train_scenes * IMAGES_PER_SCENE))
    if size.traced_train_images:
        source = parts.render_split(train_split.with_name(f"{train_split.name}_for_tracing"), size.traced_train_images,
                                    seed + TRACED_TRAIN_SEED_OFFSET, progress)
        path_trace_split(source, traced_split_of(train_split), PathTraceSettings(seed=TRACED_TRAIN_LOOK_SEED),
                         progress=progress)
    test_split = parts.render_split(out_dir / "test", size.test_images_per_object, seed + TEST_SEED_OFFSET, progress)
    return train_split, test_split


def _render_processes(images: int) -> int:
    """One process per core (at most :data:`RENDER_PROCESSES`) for a split worth it, else one."""
    return min(RENDER_PROCESSES, os.cpu_count() or 1) if images >= MIN_IMAGES_PER_PROCESS_START else 1


def in_processes(render: Callable[..., Path], progress: bool, processes: int) -> Path:
    """Call ``render(progress, shard=(i, n))`` for the n shards of a split in n processes, then once more in this
    one, which renders whatever a shard left and writes the split's JSON from every image's record (shards
    finishing together could race there).

    Rendering runs on one core per process (llvmpipe; on a GPU, pyrender's Python), so a 2-core machine renders
    twice as fast.
    """
    if processes > 1:
        with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn")) as pool:
            shards = [pool.submit(render, progress and index == 0, shard=(index, processes))
                      for index in range(processes)]
            for shard in shards:
                shard.result()
    return render(False)


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
                    out_dir: Path, code: CodeConfig | None = None) -> Config:
    """The training config of one model of the run: the size's settings, this model's data and output.

    ``train.loss`` chooses the population code's loss; the other representations keep their own. ``code``
    replaces the size's grid for this model's objects (:mod:`popcode_trainer.demo.group_codes`). Every model of
    the run caches its crops beside the training split, so the models of one object group decode them once.
    """
    loss = size.config.train.loss if representation == Representation.POPULATION_CODE else TrainConfig.loss
    splits, weights = [str(split)], [1.0 - size.scene_share - size.traced_share]
    for folder, share in ((traced_split_of(split), size.traced_share), (scene_split_of(split), size.scene_share)):
        if share:
            splits.append(str(folder))
            weights.append(share)
    if len(splits) == 1:
        weights = []
    config = replace(size.config, code=code or size.config.code,
                     data=replace(size.config.data, splits=tuple(splits), split_weights=tuple(weights),
                                  obj_ids=tuple(obj_ids),
                                  models_dir=str(split / BUILTIN_MODELS_FOLDER),
                                  num_workers=loader_workers(size.config),
                                  cache_dir=str(split.parent / CROP_CACHE_FOLDER)),
                     train=replace(size.config.train, representation=representation, out_dir=str(out_dir), loss=loss))
    return Config.from_dict(config.to_dict())  # checked like a config file


def loader_workers(config: Config) -> int:
    """The size's loader workers, or on a CUDA device with none set, one per spare core (at most
    :data:`GPU_LOADER_WORKERS`): the GPU's step is faster than one core prepares crops."""
    if config.data.num_workers or config.train.device == "cpu" or not torch.cuda.is_available():
        return config.data.num_workers
    return max(0, min(GPU_LOADER_WORKERS, (os.cpu_count() or 1) - 2))


def run_dir(out_dir: Path, representation: str, obj_ids: Sequence[int]) -> Path:
    """Where one model's checkpoints, metrics and ONNX files live."""
    return out_dir / "runs" / f"{representation}_{'-'.join(map(str, obj_ids))}"


def train_first_epoch(size: PipelineSize, representation: str, obj_ids: Sequence[int], split: Path,
                      out_dir: Path, code: CodeConfig | None = None) -> float:
    """Train the first epoch of one model of ``size``; returns its seconds (training loop, validation, checkpoint)
    without the step's compile, which later epochs do not repeat.

    :func:`train_and_export` later resumes it to the epochs it is given, which is the same as training them
    in one go when the first epoch's rate does not depend on the run's length
    (:func:`~popcode_trainer.train.schedule.first_epoch_rate_is_fixed`). A folder that already holds a checkpoint
    is kept, and its first epoch's training loop (from its metrics) is returned.
    """
    folder = run_dir(out_dir, representation, obj_ids)
    if (folder / LAST_CHECKPOINT).exists():
        return first_epoch_seconds(folder)
    config = training_config(size, representation, obj_ids, split, folder, code)
    data = build_training_data(config)
    started = time.perf_counter()
    train(config, data.representation, data.train_set, data.val_set, val_instances=data.val_instances,
          stop_after_epoch=1)
    return time.perf_counter() - started - first_epoch_compile_seconds(folder)


def train_and_export(size: PipelineSize, representation: str, obj_ids: Sequence[int], split: Path, out_dir: Path,
                     quantisations: tuple[str, ...] = (), code: CodeConfig | None = None) -> tuple[Path, float]:
    """Train (resuming an interrupted run) and export one model; returns the float ONNX path and the seconds.

    Quantised variants are written beside it as ``model.<kind>.onnx``; ``code`` as in :func:`training_config`.
    """
    folder = run_dir(out_dir, representation, obj_ids)
    onnx_path = folder / MODEL_FILE
    config = training_config(size, representation, obj_ids, split, folder, code)
    if config.train.compile == "auto" and (folder / LAST_CHECKPOINT).exists():
        # "auto" weighs a compile against the run's length, which the fit changed: keep the first epoch's choice,
        # whose epoch cost the fit measured (a compile that failed there is not tried again).
        compiled = checkpoint.load(folder / LAST_CHECKPOINT).get("step_path", {}).get("compiled", False)
        config = replace(config, train=replace(config.train, compile="on" if compiled else "off"))
    started = time.perf_counter()
    quantised = [folder / f"{onnx_path.stem}.{kind}.onnx" for kind in quantisations]
    if not onnx_path.exists() or not all(path.exists() for path in quantised):
        split = read_training_split(config)  # read once for training, parity crops and calibration
        data = build_training_data(config, split=split)
        train(config, data.representation, data.train_set, data.val_set,
              resume=(folder / LAST_CHECKPOINT).exists(), val_instances=data.val_instances)
        crops, obj_ids = validation_crops(config, split=split)
        trained = load_trained_model(folder / LAST_CHECKPOINT)
        calibrator, _ = calibrate_checkpoint(trained, split=split)
        export_trained(trained, onnx_path, crops, quantisations, obj_ids=obj_ids, calibrator=calibrator)
    return onnx_path, time.perf_counter() - started
