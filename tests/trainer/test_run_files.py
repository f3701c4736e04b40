"""The one reader of a run's ``metrics.csv``: what the training loop writes reads back, a bad file is named."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from popcode_runtime import PopcodeError
from popcode_trainer.train import epoch_record
from popcode_trainer.train.run_files import METRICS_FILE, EpochMetrics, read_metrics

ROWS = [EpochMetrics(1, 0.9, 1.1, 40.0, 35.5, 120.0, 12.25), EpochMetrics(2, 0.5, 0.7, 20.0, 18.0, 130.0, 11.5)]


def test_reads_back_what_the_loop_writes(tmp_path: Path) -> None:
    for row in ROWS:
        epoch_record.append_metrics(tmp_path / METRICS_FILE, row)
    by_folder = read_metrics(tmp_path, ("seconds", "val_error_median_deg"))
    by_file = read_metrics(tmp_path / METRICS_FILE)
    assert list(by_folder) == [field.name for field in dataclasses.fields(EpochMetrics)]
    for name, column in by_folder.items():
        assert column.dtype == np.float64
        np.testing.assert_array_equal(column, [getattr(row, name) for row in ROWS])
        np.testing.assert_array_equal(by_file[name], column)


@pytest.mark.parametrize(("text", "message"), [
    (None, r"metrics.csv: cannot read the training metrics \(No such file"),
    ("", "metrics.csv has no epochs"),
    ("epoch,seconds\n", "metrics.csv has no epochs"),
    ("epoch,train_loss\n1,0.5\n", r"metrics.csv has no column seconds \(it has epoch, train_loss\)"),
    ("epoch,seconds\n1,2.0\n2\n", "metrics.csv, line 3: 1 values for the 2 columns"),
    ("epoch,seconds\n1,fast\n", "metrics.csv: a value is not a number"),
])
def test_a_bad_file_is_named(tmp_path: Path, text: str | None, message: str) -> None:
    if text is not None:
        (tmp_path / METRICS_FILE).write_text(text)
    with pytest.raises(PopcodeError, match=message):
        read_metrics(tmp_path, ("seconds",))
