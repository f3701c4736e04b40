"""What each epoch of a training run leaves on disk: a row of ``metrics.csv``, the last (and best) checkpoint,
TensorBoard scalars and one line; and, on resume, the metrics cut back to the checkpoint.

The row is written before the checkpoint, so a run killed between the two has
one row too many, which :func:`truncate_metrics` drops when it resumes.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path
from typing import Any

import torch
from torch import nn
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import append_synced, csv_text, write_bytes_atomic

from . import checkpoint
from .config import Config
from .fast_path import StepPath
from .network import NetworkConfig
from .run_files import BEST_CHECKPOINT, LAST_CHECKPOINT, METRICS_FILE, EpochMetrics

METRICS_COLUMNS = [f.name for f in dataclasses.fields(EpochMetrics)]


def append_metrics(path: Path, row: EpochMetrics) -> None:
    """One row, synced: the checkpoint written after it must never be on disk without it."""
    append_synced(path, csv_text([dataclasses.astuple(row)]), first=csv_text([METRICS_COLUMNS]))


def truncate_metrics(path: Path, last_epoch: int) -> None:
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
    rows = [[old[name] if name in old else defaults[name] for name in METRICS_COLUMNS] for old in kept]
    write_bytes_atomic(path, csv_text([METRICS_COLUMNS, *rows]).encode())


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


class EpochRecord:
    """The main rank's record of each epoch: its metrics row, the last (and best) checkpoint, TensorBoard, a line."""

    def __init__(self, config: Config, representation_metadata: dict[str, Any], net_config: NetworkConfig,
                 model: nn.Module, optimizer: torch.optim.Optimizer, scaler: torch.amp.GradScaler) -> None:
        self.config, self.net_config = config, net_config
        self.model, self.optimizer, self.scaler = model, optimizer, scaler
        self.out_dir = Path(config.train.out_dir)
        self.tensorboard = _TensorBoard(self.out_dir)
        self.revision = checkpoint.git_revision()
        self.metadata = checkpoint.metadata_props(representation_metadata, net_config.input_size,
                                                  config.data.models_dir)

    def save(self, row: EpochMetrics, path: StepPath, best_error: float, validated: bool) -> float:
        """Record ``row``; returns the best validation error so far."""
        improved = row.val_error_mean_deg < best_error
        best_error = min(best_error, row.val_error_mean_deg) if validated else best_error
        state = {
            "epoch": row.epoch,
            "config": self.config.to_dict(),
            "network": dataclasses.asdict(self.net_config),
            "metadata": self.metadata,
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "scaler": self.scaler.state_dict(),
            "rng": checkpoint.rng_state(),
            "best_val_error_deg": best_error,
            "git_revision": self.revision,
            "step_path": path.to_dict(),
        }
        append_metrics(self.out_dir / METRICS_FILE, row)  # before the checkpoint: resume truncates extra rows
        checkpoint.save_atomic(state, self.out_dir / LAST_CHECKPOINT)
        if improved:
            checkpoint.save_atomic(state, self.out_dir / BEST_CHECKPOINT)
        self.tensorboard.log(row)
        tqdm.write(f"epoch {row.epoch}: train loss {row.train_loss:.4g}, val loss {row.val_loss:.4g}, "
                   f"val error mean {row.val_error_mean_deg:.2f} deg, median {row.val_error_median_deg:.2f} "
                   f"deg, {row.samples_per_s:.1f} samples/s")
        return best_error
