"""The training loop: set-up -> (resume) -> epochs of batches -> validation -> checkpoint.

Runs as one process or under ``torchrun`` (DDP). ``train.batch_size`` is the
global batch, split evenly over ranks, so the paper's batch of 64 means the
same thing on one CPU and on eight GPUs. Everything random in an epoch is
seeded from ``(seed, epoch)``, which makes ``--resume`` continue bit-exactly.
"""

from __future__ import annotations

import dataclasses
import math
import random
import time
from collections.abc import Sequence
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from torch.utils.data import DataLoader, Dataset
from torch.utils.data.distributed import DistributedSampler
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_json_atomic
from popcode_runtime.base.output_lock import OutputLock
from popcode_runtime.model.metadata import RotationFrame

from . import allocator, checkpoint, distributed, fast_path, pretrained
from .config import Config
from .epoch_record import EpochRecord, truncate_metrics
from .network import NetworkConfig, build_network, check_trainable
from .representations import InstanceLike, OutputRepresentation
from .run_files import LAST_CHECKPOINT, METRICS_FILE, RUN_LOCK, START_FILE, EpochMetrics
from .schedule import learning_rate


def network_config(config: Config, representation: OutputRepresentation) -> NetworkConfig:
    """The network config with the fields that follow from the representation and the crop."""
    return dataclasses.replace(config.network, output_dim=representation.output_dim,
                               input_size=config.data.crop_size)


def _loader(dataset: Dataset, batch_size: int, context: distributed.Context, seed: int, epoch: int,
            num_workers: int, train: bool) -> DataLoader:
    """A loader whose order and worker seeds depend only on (seed, epoch)."""
    generator = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    sampler = None
    if context.distributed:
        sampler = DistributedSampler(dataset, num_replicas=context.world_size, rank=context.rank,
                                     shuffle=train, seed=seed, drop_last=train)
        sampler.set_epoch(epoch)
    return DataLoader(dataset, batch_size=batch_size, shuffle=train and sampler is None, sampler=sampler,
                      generator=generator, num_workers=num_workers, drop_last=train,
                      persistent_workers=False, pin_memory=context.device.type == "cuda")


def _true_rotations(batch: dict[str, Any], representation: OutputRepresentation,
                    instances: Sequence[InstanceLike] | None) -> np.ndarray:
    """Ground truth in the model's frame; allocentric needs each instance's K and box."""
    R_m2c = batch["R_m2c"].double().numpy()
    if representation.metadata.rotation_frame == RotationFrame.EGOCENTRIC:
        return R_m2c
    if instances is None:
        raise PopcodeError("validating an allocentric model needs the validation instances (for K and boxes)")
    found = [instances[int(i)] for i in batch["index"]]
    return np.stack([representation.frame_rotation(R, inst.K, inst.box) for R, inst in zip(R_m2c, found,
                                                                                           strict=True)])


@torch.no_grad()
def validate(model: nn.Module, loader: DataLoader, representation: OutputRepresentation,
             context: distributed.Context, instances: Sequence[InstanceLike] | None = None,
             ) -> tuple[float, np.ndarray]:
    """Mean loss and every rotation error [rad] up to symmetry over the (sharded) validation set."""
    model.eval()
    loss_sum, count, errors = 0.0, 0, []
    for batch in loader:
        output = model(batch["image"].to(context.device)).float()
        target = batch["target"].to(context.device)
        loss_sum += float(representation.loss(output, target, 1.0)) * len(target)
        count += len(target)
        R_pred = representation.decode(output.cpu().numpy()).R
        R_true = _true_rotations(batch, representation, instances)
        errors += representation.errors_rad(R_pred, R_true, batch["obj_id"].numpy()).tolist()
    model.train()
    loss_sum, count = distributed.sum_over_ranks([loss_sum, float(count)], context)
    return loss_sum / max(count, 1.0), np.asarray(distributed.gather_lists(errors, context))


def run_lock(out_dir: str | Path) -> AbstractContextManager[object]:
    """Hold ``<out_dir>/train.lock`` (the folder made here) while a run writes the folder, so that a second run
    into it is refused. Under ``torchrun`` only rank 0 holds it: the other ranks write nothing there, and their own
    rank 0's lock would refuse them."""
    if distributed.launched_rank() != 0:
        return nullcontext()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return OutputLock(out_dir / RUN_LOCK, f"another process is training into {out_dir} (it holds {RUN_LOCK}); "
                                          "wait for it to end, or train into another folder (train: --set "
                                          "train.out_dir=DIR; demo: another --out)")


def train(config: Config, representation: OutputRepresentation, train_set: Dataset, val_set: Dataset | None = None,
          resume: bool = False, val_instances: Sequence[InstanceLike] | None = None,
          stop_after_epoch: int | None = None, locked: bool = False) -> list[EpochMetrics]:
    """Train (or resume) per ``config``; writes checkpoints and metrics to ``config.train.out_dir``.

    ``train_set``/``val_set`` yield dicts with ``image`` (1, S, S), ``target``,
    ``R_m2c``, ``obj_id`` and ``index`` (the ``CropDataset`` contract);
    ``val_instances[index]`` gives K and the box for allocentric validation.
    ``stop_after_epoch`` ends the call after that epoch (checkpointed) of a run of ``train.epochs``: the rate
    schedule still sees the whole run, and a later call resumes it. ``locked``: the caller holds the run folder's
    lock already (:func:`run_lock`); else this call holds it.
    Returns the metrics of the epochs this call ran.
    """
    cfg = config.train
    with (nullcontext() if locked else run_lock(cfg.out_dir)):
        context = distributed.setup(cfg.device)
        try:
            history = _run(config, representation, train_set, val_set, resume, val_instances, context,
                           stop_after_epoch)
        except BaseException:
            distributed.teardown(context)
            raise
        distributed.teardown(context, finished=True)
    return history


def _run(config: Config, representation: OutputRepresentation, train_set: Dataset, val_set: Dataset | None,
         resume: bool, val_instances: Sequence[InstanceLike] | None,
         context: distributed.Context, stop_after_epoch: int | None = None) -> list[EpochMetrics]:
    cfg = config.train
    if cfg.batch_size % context.world_size:
        raise PopcodeError(f"train.batch_size {cfg.batch_size} must be divisible by the {context.world_size} ranks")
    rank_batch = cfg.batch_size // context.world_size
    trainee = _set_up(config, representation, len(train_set), rank_batch, context)
    start_epoch, best_error = _start(config, trainee, resume, context)
    # DDP averages gradients across ranks in backward; every rank steps the same optimizer state.
    forward = fast_path.GuardedForward(DistributedDataParallel(trainee.model) if context.distributed
                                       else trainee.model, trainee.path)
    if context.is_main:
        tqdm.write(f"training step: {trainee.path.describe()}"
                   + ("; freed memory kept for the next step" if trainee.memory_kept else ""))
    saver = EpochRecord(config, representation.metadata, trainee.net_config, trainee.model, trainee.optimizer,
                        trainee.scaler) if context.is_main else None
    history = []
    for epoch in range(start_epoch, cfg.epochs if stop_after_epoch is None else min(cfg.epochs, stop_after_epoch)):
        loss_sum, seen, seconds, compile_s = _train_epoch(config, representation, trainee, forward, train_set,
                                                          rank_batch, context, epoch)
        val_loss, errors_deg = math.nan, np.array([])
        if val_set is not None and len(val_set) > 0:
            val_loader = _loader(val_set, rank_batch, context, cfg.seed, epoch, config.data.num_workers, train=False)
            val_loss, errors_rad = validate(trainee.model, val_loader, representation, context, val_instances)
            errors_deg = np.degrees(errors_rad)
        row = EpochMetrics(
            epoch=epoch + 1, train_loss=loss_sum / seen, val_loss=val_loss,
            val_error_mean_deg=float(errors_deg.mean()) if errors_deg.size else math.nan,
            val_error_median_deg=float(np.median(errors_deg)) if errors_deg.size else math.nan,
            samples_per_s=seen / seconds, seconds=seconds, compile_seconds=compile_s,
        )
        history.append(row)
        if saver is not None:
            best_error = saver.save(row, forward.path, best_error, validated=bool(errors_deg.size))
    return history


@dataclasses.dataclass
class _Trainee:
    """The network of a run and what steps it, set up once."""

    net_config: NetworkConfig
    model: nn.Module
    optimizer: torch.optim.Optimizer
    scaler: torch.amp.GradScaler
    use_amp: bool
    path: fast_path.StepPath
    memory_kept: bool


def _set_up(config: Config, representation: OutputRepresentation, crops: int, rank_batch: int,
            context: distributed.Context) -> _Trainee:
    """Seeds, network, the step's path, optimizer and scaler: everything before a resume."""
    cfg = config.train
    memory_kept = allocator.keep_freed_memory()
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    net_config = network_config(config, representation)
    check_trainable(net_config, rank_batch)
    path = fast_path.choose_path(cfg.precision, cfg.compile, context.device, cfg.epochs * (crops // rank_batch),
                                 conv_widths=net_config.conv_channels)
    model = build_network(net_config).to(context.device)
    if path.channels_last:
        model = model.to(memory_format=torch.channels_last)
    # two groups only where the start's weights get their own rate: a run of one group resumes as it was saved
    parameters = pretrained.parameter_groups(model) if cfg.init_lr_scale != 1.0 else model.parameters()
    optimizer = fast_path.adam(parameters, cfg.lr, context.device)
    use_amp = cfg.amp and context.device.type == "cuda"
    scaler = torch.amp.GradScaler(context.device.type, enabled=use_amp)
    return _Trainee(net_config, model, optimizer, scaler, use_amp, path, memory_kept)


def _start(config: Config, trainee: _Trainee, resume: bool, context: distributed.Context) -> tuple[int, float]:
    """The first epoch to train and the best validation error so far: a resumed run's, from its last checkpoint
    (refused when the config differs), or a fresh start (refused over an earlier run's folder)."""
    out_dir = Path(config.train.out_dir)
    if resume:
        state = checkpoint.load(out_dir / LAST_CHECKPOINT)
        differences = checkpoint.config_differences(state["config"], config.to_dict(), Config().to_dict())
        if differences:
            raise PopcodeError(f"cannot resume {out_dir / LAST_CHECKPOINT}: the config differs "
                               f"({'; '.join(differences)}); use the run's config or a new train.out_dir")
        trainee.model.load_state_dict(state["model"])
        trainee.optimizer.load_state_dict(state["optimizer"])
        trainee.scaler.load_state_dict(state["scaler"])
        checkpoint.restore_rng_state(state["rng"])
        start_epoch = int(state["epoch"])
        if context.is_main:
            truncate_metrics(out_dir / METRICS_FILE, start_epoch)
        return start_epoch, float(state["best_val_error_deg"])
    if (out_dir / LAST_CHECKPOINT).exists():
        raise PopcodeError(f"{out_dir} already holds a run; continue it with train --resume, or train into another "
                           "folder (--set train.out_dir=DIR)")
    start, line = pretrained.resolve_start(config.train.init, trainee.net_config)
    if start is not None:
        pretrained.apply_start(trainee.model, start, trainee.net_config)
        if config.train.init_lr_scale != 1.0:
            trainee.optimizer.param_groups[0]["lr_scale"] = config.train.init_lr_scale
    if context.is_main:
        (out_dir / METRICS_FILE).unlink(missing_ok=True)  # rows of a run killed before its first checkpoint
        write_json_atomic(out_dir / START_FILE, {"init": config.train.init, "start": line,
                                                 "path": None if start is None else str(start.path),
                                                 "card": None if start is None else start.card})
        tqdm.write(f"first weights: {line}")
    return 0, math.inf


def _train_epoch(config: Config, representation: OutputRepresentation, trainee: _Trainee,
                 forward: fast_path.GuardedForward, train_set: Dataset, rank_batch: int, context: distributed.Context,
                 epoch: int) -> tuple[float, float, float, float]:
    """One epoch of steps: the loss summed over every rank's crops, their count, the seconds it took and the
    seconds of it spent compiling."""
    cfg = config.train
    if hasattr(train_set, "set_epoch"):
        train_set.set_epoch(epoch)
    loader = _loader(train_set, rank_batch, context, cfg.seed, epoch, config.data.num_workers, train=True)
    steps = len(loader)
    if steps == 0:
        raise PopcodeError(f"the training set ({len(train_set)} crops) is smaller than one batch per rank "
                           f"({rank_batch}); lower train.batch_size")
    started, compiled_before = time.perf_counter(), forward.compile_s
    loss_sum, seen = 0.0, 0
    bar = tqdm(loader, desc=f"epoch {epoch + 1}/{cfg.epochs}", disable=not context.is_main, leave=False)
    for step, batch in enumerate(bar):
        image = fast_path.to_layout(batch["image"].to(context.device, non_blocking=True), forward.path)
        target = batch["target"].to(context.device, non_blocking=True)
        step_rate = learning_rate(cfg.lr, cfg.schedule, epoch + step / steps, cfg.epochs, cfg.warmup_epochs)
        for group in trainee.optimizer.param_groups:
            group["lr"] = step_rate * group.get("lr_scale", 1.0)
        with fast_path.autocast(forward.path, context.device, trainee.use_amp):
            output = forward(image)
        loss = representation.loss(output.float(), target, (epoch + step / steps) / cfg.epochs)
        trainee.optimizer.zero_grad(set_to_none=True)
        trainee.scaler.scale(loss).backward()
        trainee.scaler.step(trainee.optimizer)
        trainee.scaler.update()
        loss_sum += float(loss.detach()) * len(image)
        seen += len(image)
        rate = seen * context.world_size / (time.perf_counter() - started)
        bar.set_postfix(loss=f"{loss_sum / seen:.4g}", samples_per_s=f"{rate:.1f}", refresh=False)
    loss_sum, seen = distributed.sum_over_ranks([loss_sum, float(seen)], context)
    return loss_sum, seen, time.perf_counter() - started, forward.compile_s - compiled_before
