"""The training loop: set-up -> (resume) -> epochs of batches -> validation -> checkpoint.

Runs as one process or under ``torchrun`` (DDP). ``train.batch_size`` is the
global batch, split evenly over ranks, so the paper's batch of 64 means the
same thing on one CPU and on eight GPUs. Everything random in an epoch is
seeded from ``(seed, epoch)``, which makes ``--resume`` continue bit-exactly.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import random
import time
from collections.abc import Sequence
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
from popcode_runtime.model.metadata import RotationFrame

from . import allocator, checkpoint, distributed, fast_path
from .config import Config
from .network import NetworkConfig, build_network, feature_side
from .representations import InstanceLike, OutputRepresentation
from .run_files import BEST_CHECKPOINT, LAST_CHECKPOINT, METRICS_FILE, EpochMetrics
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


METRICS_COLUMNS = [f.name for f in dataclasses.fields(EpochMetrics)]


def _append_metrics(path: Path, row: EpochMetrics) -> None:
    new = not path.exists() or path.stat().st_size == 0
    with path.open("a", newline="") as handle:
        writer = csv.writer(handle)
        if new:
            writer.writerow(METRICS_COLUMNS)
        writer.writerow(dataclasses.astuple(row))


def _truncate_metrics(path: Path, last_epoch: int) -> None:
    """On resume: drop rows a crashed run wrote after its last checkpoint, so the log matches the state, and give
    the rows of an older trainer the columns added since, at their defaults."""
    if not path.exists():
        return
    with path.open(newline="") as handle:
        rows = [row for row in csv.reader(handle) if row]
    if not rows:
        return
    defaults = {f.name: f.default for f in dataclasses.fields(EpochMetrics) if f.default is not dataclasses.MISSING}
    lacking = [name for name in METRICS_COLUMNS if name not in rows[0] and name not in defaults]
    if lacking:
        raise PopcodeError(f"{path} has no column {', '.join(lacking)}: not the metrics of a popcode training run")
    kept = [dict(zip(rows[0], row, strict=False)) for row in rows[1:] if int(row[0]) <= last_epoch]
    temporary = path.with_name(f".{path.name}.tmp")
    with temporary.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(METRICS_COLUMNS)
        writer.writerows([[old[name] if name in old else defaults[name] for name in METRICS_COLUMNS] for old in kept])
    temporary.replace(path)


class _TensorBoard:
    """Scalars to TensorBoard when it is installed; nothing otherwise."""

    def __init__(self, out_dir: Path) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            self.writer = None
        else:
            self.writer = SummaryWriter(str(out_dir / "tensorboard"))

    def log(self, row: EpochMetrics) -> None:
        if self.writer is None:
            return
        for name, value in dataclasses.asdict(row).items():
            if name != "epoch" and math.isfinite(value):
                self.writer.add_scalar(name, value, row.epoch)
        self.writer.flush()


def train(config: Config, representation: OutputRepresentation, train_set: Dataset, val_set: Dataset | None = None,
          resume: bool = False, val_instances: Sequence[InstanceLike] | None = None,
          stop_after_epoch: int | None = None) -> list[EpochMetrics]:
    """Train (or resume) per ``config``; writes checkpoints and metrics to ``config.train.out_dir``.

    ``train_set``/``val_set`` yield dicts with ``image`` (1, S, S), ``target``,
    ``R_m2c``, ``obj_id`` and ``index`` (the ``CropDataset`` contract);
    ``val_instances[index]`` gives K and the box for allocentric validation.
    ``stop_after_epoch`` ends the call after that epoch (checkpointed) of a run of ``train.epochs``: the rate
    schedule still sees the whole run, and a later call resumes it.
    Returns the metrics of the epochs this call ran.
    """
    cfg = config.train
    context = distributed.setup(cfg.device)
    try:
        history = _run(config, representation, train_set, val_set, resume, val_instances, context, stop_after_epoch)
    except BaseException:
        distributed.teardown(context)
        raise
    distributed.teardown(context, finished=True)
    return history


def _run(config: Config, representation: OutputRepresentation, train_set: Dataset, val_set: Dataset | None,
         resume: bool, val_instances: Sequence[InstanceLike] | None,
         context: distributed.Context, stop_after_epoch: int | None = None) -> list[EpochMetrics]:
    cfg = config.train
    out_dir = Path(cfg.out_dir)
    if cfg.batch_size % context.world_size:
        raise PopcodeError(f"train.batch_size {cfg.batch_size} must be divisible by the {context.world_size} ranks")
    rank_batch = cfg.batch_size // context.world_size
    memory_kept = allocator.keep_freed_memory()
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)

    net_config = network_config(config, representation)
    if rank_batch == 1 and feature_side(net_config) == 1:
        raise PopcodeError(f"the trunk ends at 1x1 for data.crop_size {config.data.crop_size}, where BatchNorm needs "
                           f"two crops per rank: raise train.batch_size or data.crop_size")
    path = fast_path.choose_path(cfg.precision, cfg.compile, context.device,
                                 cfg.epochs * (len(train_set) // rank_batch), conv_widths=net_config.conv_channels)
    model = build_network(net_config).to(context.device)
    if path.channels_last:
        model = model.to(memory_format=torch.channels_last)
    optimizer = fast_path.adam(model.parameters(), cfg.lr, context.device)
    use_amp = cfg.amp and context.device.type == "cuda"
    scaler = torch.amp.GradScaler(context.device.type, enabled=use_amp)
    start_epoch, best_error = 0, math.inf

    if resume:
        state = checkpoint.load(out_dir / LAST_CHECKPOINT)
        differences = checkpoint.config_differences(state["config"], config.to_dict(), Config().to_dict())
        if differences:
            raise PopcodeError(f"cannot resume {out_dir / LAST_CHECKPOINT}: the config differs "
                               f"({'; '.join(differences)}); use the run's config or a new train.out_dir")
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scaler.load_state_dict(state["scaler"])
        checkpoint.restore_rng_state(state["rng"])
        start_epoch, best_error = int(state["epoch"]), float(state["best_val_error_deg"])
        if context.is_main:
            _truncate_metrics(out_dir / METRICS_FILE, start_epoch)
    elif (out_dir / LAST_CHECKPOINT).exists():
        raise PopcodeError(f"{out_dir} already holds a run; pass --resume to continue it or choose a new out_dir")
    elif context.is_main:
        (out_dir / METRICS_FILE).unlink(missing_ok=True)  # rows of a run killed before its first checkpoint

    # DDP averages gradients across ranks in backward; every rank steps the same optimizer state.
    trained = DistributedDataParallel(model) if context.distributed else model
    forward = fast_path.GuardedForward(trained, path)
    if context.is_main:
        tqdm.write(f"training step: {path.describe()}" + ("; freed memory kept for the next step" if memory_kept
                                                           else ""))
    if context.is_main:
        out_dir.mkdir(parents=True, exist_ok=True)
    tensorboard = _TensorBoard(out_dir) if context.is_main else None
    revision = checkpoint.git_revision() if context.is_main else ""
    metadata = checkpoint.metadata_props(representation.metadata, net_config.input_size,
                                         config.data.models_dir) if context.is_main else {}
    history = []
    for epoch in range(start_epoch, cfg.epochs if stop_after_epoch is None else min(cfg.epochs, stop_after_epoch)):
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
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(cfg.lr, cfg.schedule, epoch + step / steps, cfg.epochs, cfg.warmup_epochs)
            with fast_path.autocast(forward.path, context.device, use_amp):
                output = forward(image)
            loss = representation.loss(output.float(), target, (epoch + step / steps) / cfg.epochs)
            optimizer.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()
            scaler.step(optimizer)
            scaler.update()
            loss_sum += float(loss.detach()) * len(image)
            seen += len(image)
            rate = seen * context.world_size / (time.perf_counter() - started)
            bar.set_postfix(loss=f"{loss_sum / seen:.4g}", samples_per_s=f"{rate:.1f}", refresh=False)
        loss_sum, seen = distributed.sum_over_ranks([loss_sum, float(seen)], context)
        seconds = time.perf_counter() - started

        val_loss, errors_deg = math.nan, np.array([])
        if val_set is not None and len(val_set) > 0:
            val_loader = _loader(val_set, rank_batch, context, cfg.seed, epoch, config.data.num_workers, train=False)
            val_loss, errors_rad = validate(model, val_loader, representation, context, val_instances)
            errors_deg = np.degrees(errors_rad)
        row = EpochMetrics(
            epoch=epoch + 1, train_loss=loss_sum / seen, val_loss=val_loss,
            val_error_mean_deg=float(errors_deg.mean()) if errors_deg.size else math.nan,
            val_error_median_deg=float(np.median(errors_deg)) if errors_deg.size else math.nan,
            samples_per_s=seen / seconds, seconds=seconds, compile_seconds=forward.compile_s - compiled_before,
        )
        history.append(row)
        if context.is_main:
            improved = row.val_error_mean_deg < best_error
            best_error = min(best_error, row.val_error_mean_deg) if errors_deg.size else best_error
            state = {
                "epoch": epoch + 1,
                "config": config.to_dict(),
                "network": dataclasses.asdict(net_config),
                "metadata": metadata,
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "scaler": scaler.state_dict(),
                "rng": checkpoint.rng_state(),
                "best_val_error_deg": best_error,
                "git_revision": revision,
                "step_path": forward.path.to_dict(),
            }
            _append_metrics(out_dir / METRICS_FILE, row)  # before the checkpoint: resume truncates extra rows
            checkpoint.save_atomic(state, out_dir / LAST_CHECKPOINT)
            if improved:
                checkpoint.save_atomic(state, out_dir / BEST_CHECKPOINT)
            tensorboard.log(row)
            tqdm.write(f"epoch {row.epoch}: train loss {row.train_loss:.4g}, val loss {row.val_loss:.4g}, "
                       f"val error mean {row.val_error_mean_deg:.2f} deg, median {row.val_error_median_deg:.2f} "
                       f"deg, {row.samples_per_s:.1f} samples/s")
    return history
