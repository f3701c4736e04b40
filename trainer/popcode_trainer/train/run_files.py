"""What a training run's folder holds, by name: the trainer writes these files; demo, export and figures read them.

The rows of ``metrics.csv`` (:class:`EpochMetrics`) and its one reader live here too, so the columns' names
exist once and reading them needs no torch.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from popcode_runtime.base.errors import PopcodeError

LAST_CHECKPOINT = "last.pt"  # written after every epoch; --resume continues from it
BEST_CHECKPOINT = "best.pt"  # the epoch with the lowest validation error
METRICS_FILE = "metrics.csv"  # one row per epoch (EpochMetrics)
MODEL_FILE = "model.onnx"  # the exported float model; quantised ones beside it as model.<kind>.onnx
CROP_CACHE_FOLDER = "crop_cache"  # the decoded training crops (data.crop_cache); safe to delete
START_FILE = "start.json"  # which first weights the run took (train.pretrained): random or a pretrained start
RUN_LOCK = "train.lock"  # held while a process trains into the folder (train.loop.run_lock); left by a killed one


@dataclass(frozen=True)
class EpochMetrics:
    """One row of ``metrics.csv``; errors are up to symmetry, in the model's rotation frame."""

    epoch: int
    train_loss: float
    val_loss: float
    val_error_mean_deg: float
    val_error_median_deg: float
    samples_per_s: float
    seconds: float
    compile_seconds: float = 0.0  # of ``seconds``, compiling the step (a one-time cost; metrics of older runs lack it)


def read_metrics(run: str | Path, columns: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """Each column of a run's ``metrics.csv`` as a float array, one value per epoch; ``columns`` are those the
    caller reads, refused when missing. ``run`` is the run folder, or the file itself (a ``.csv`` path).

    The one reader of what :mod:`.loop` writes, beside the columns' names (:class:`EpochMetrics`), so demo,
    figures and bench cannot each parse it their own way.
    """
    path = Path(run)
    if path.suffix != ".csv":
        path = path / METRICS_FILE
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            rows = [row for row in csv.reader(handle) if row]
    except OSError as error:
        raise PopcodeError(f"{path}: cannot read the training metrics ({error.strerror or error})") from error
    except (csv.Error, UnicodeDecodeError) as error:
        raise PopcodeError(f"{path}: not a training metrics file ({error})") from error
    if len(rows) < 2:
        raise PopcodeError(f"{path} has no epochs")
    header, values = rows[0], rows[1:]
    missing = [name for name in columns if name not in header]
    if missing:
        raise PopcodeError(f"{path} has no column {', '.join(missing)} (it has {', '.join(header)})")
    for line, row in enumerate(values, start=2):
        if len(row) != len(header):
            raise PopcodeError(f"{path}, line {line}: {len(row)} values for the {len(header)} columns")
    try:
        table = np.array(values, dtype=np.float64)
    except ValueError as error:
        raise PopcodeError(f"{path}: a value is not a number ({error})") from error
    return {name: table[:, k] for k, name in enumerate(header)}
