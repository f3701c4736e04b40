"""The training loop: it learns, it resumes exactly, it refuses to resume another config."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny import tiny_config, tiny_data, tiny_representation

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.model.metadata import Representation, RotationFrame
from popcode_trainer.train import checkpoint
from popcode_trainer.train.loop import train
from popcode_trainer.train.run_files import BEST_CHECKPOINT, LAST_CHECKPOINT, METRICS_FILE, read_metrics
from popcode_trainer.train.schedule import first_epoch_rate_is_fixed, learning_rate


@pytest.mark.parametrize("name", Representation.values())
def test_a_few_epochs_reduce_the_loss(tmp_path: Path, name: str) -> None:
    config = tiny_config(tmp_path, epochs=4, representation=name)
    rep = tiny_representation(config)
    train_set, val_set = tiny_data(rep)
    history = train(config, rep, train_set, val_set)
    assert [row.epoch for row in history] == [1, 2, 3, 4]
    assert history[-1].train_loss < history[0].train_loss
    assert all(0.0 <= row.val_error_mean_deg <= 180.0 for row in history)
    with (tmp_path / METRICS_FILE).open() as handle:
        assert [int(row["epoch"]) for row in csv.DictReader(handle)] == [1, 2, 3, 4]


def test_resume_continues_exactly(tmp_path: Path) -> None:
    straight = tiny_config(tmp_path / "straight", epochs=2)
    rep = tiny_representation(straight)
    train_set, val_set = tiny_data(rep)
    train(straight, rep, train_set, val_set)

    interrupted = tiny_config(tmp_path / "interrupted", epochs=1)
    train(interrupted, rep, train_set, val_set)
    resumed = train(tiny_config(tmp_path / "interrupted", epochs=2), rep, train_set, val_set, resume=True)
    assert [row.epoch for row in resumed] == [2]

    a = checkpoint.load(tmp_path / "straight" / LAST_CHECKPOINT)
    b = checkpoint.load(tmp_path / "interrupted" / LAST_CHECKPOINT)
    assert a["epoch"] == b["epoch"] == 2
    for key, tensor in a["model"].items():
        assert torch.equal(tensor, b["model"][key]), key
    for index, state in a["optimizer"]["state"].items():
        assert torch.equal(state["exp_avg"], b["optimizer"]["state"][index]["exp_avg"])
    with (tmp_path / "interrupted" / METRICS_FILE).open() as handle:
        assert [int(row["epoch"]) for row in csv.DictReader(handle)] == [1, 2]


def test_resume_with_another_config_is_refused(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, epochs=1)
    rep = tiny_representation(config)
    train_set, _ = tiny_data(rep, val_count=0)
    train(config, rep, train_set)
    with pytest.raises(PopcodeError, match=r"config differs \(train.lr: 0.001 -> 0.01\)"):
        train(tiny_config(tmp_path, epochs=2, lr=1e-2), rep, train_set, resume=True)
    with pytest.raises(PopcodeError, match="--resume"):
        train(config, rep, train_set)


def test_allocentric_validation_uses_the_instances(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, epochs=1, rotation_frame=RotationFrame.ALLOCENTRIC)
    rep = tiny_representation(config)
    train_set, val_set = tiny_data(rep)
    with pytest.raises(PopcodeError, match="allocentric"):
        train(config, rep, train_set, val_set)
    history = train(tiny_config(tmp_path / "b", epochs=1, rotation_frame=RotationFrame.ALLOCENTRIC), rep,
                    train_set, val_set, val_instances=val_set.instances)
    assert 0.0 <= history[0].val_error_mean_deg <= 180.0


def test_checkpoints_load_with_weights_only(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, epochs=1)
    rep = tiny_representation(config)
    train(config, rep, *tiny_data(rep))
    state = torch.load(tmp_path / LAST_CHECKPOINT, weights_only=True)
    assert state["config"] == config.to_dict()
    assert (tmp_path / BEST_CHECKPOINT).is_file()
    assert not list(tmp_path.glob(".*.tmp"))


def test_a_fresh_start_drops_rows_of_a_run_killed_before_its_first_checkpoint(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, epochs=1)
    rep = tiny_representation(config)
    train_set, _ = tiny_data(rep, val_count=0)
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / METRICS_FILE).write_text("epoch,train_loss\n1,0.5\n")  # killed mid-epoch 2: no checkpoint yet
    train(config, rep, train_set)
    with (tmp_path / METRICS_FILE).open() as handle:
        assert [int(row["epoch"]) for row in csv.DictReader(handle)] == [1]


def test_a_resume_adds_the_metrics_columns_of_a_newer_trainer(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, epochs=2)
    rep = tiny_representation(config)
    train_set, _ = tiny_data(rep, val_count=0)
    train(config, rep, train_set, stop_after_epoch=1)
    with (tmp_path / METRICS_FILE).open(newline="") as handle:
        rows = [row[:-1] for row in csv.reader(handle)]  # as an older trainer wrote it: no compile_seconds
    assert rows[0][-1] == "seconds"
    with (tmp_path / METRICS_FILE).open("w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    train(config, rep, train_set, resume=True)
    metrics = read_metrics(tmp_path)
    assert list(metrics["epoch"]) == [1, 2] and metrics["compile_seconds"][0] == 0.0
    assert metrics["seconds"][0] == float(rows[1][-1])


def test_metrics_without_a_header_or_of_something_else_are_handled(tmp_path: Path) -> None:
    config = tiny_config(tmp_path, epochs=1)
    rep = tiny_representation(config)
    train_set, _ = tiny_data(rep, val_count=0)
    tmp_path.mkdir(parents=True, exist_ok=True)
    (tmp_path / METRICS_FILE).write_text("")  # left empty by a run killed as it began
    train(config, rep, train_set)
    assert list(read_metrics(tmp_path)["epoch"]) == [1]
    other = tiny_config(tmp_path / "other", epochs=2)
    train(other, rep, train_set, stop_after_epoch=1)
    (tmp_path / "other" / METRICS_FILE).write_text("epoch,loss\n1,0.5\n")  # not what popcode writes
    with pytest.raises(PopcodeError, match=r"has no column train_loss, .*not the metrics of a popcode training"):
        train(other, rep, train_set, resume=True)


def test_learning_rate_schedules_warm_up_and_decay() -> None:
    assert learning_rate(1e-3, "constant", 7.3, 20) == 1e-3
    assert learning_rate(1e-3, "constant", 0.5, 20, warmup_epochs=1.0) == pytest.approx(5e-4)
    cosine = [learning_rate(1e-3, "cosine", e, 20, warmup_epochs=1.0) for e in np.linspace(0, 20, 81)]
    peak = int(np.argmax(cosine))
    assert cosine[0] == 0.0 and cosine[peak] == pytest.approx(1e-3) and cosine[-1] == pytest.approx(0.0, abs=1e-12)
    assert all(a <= b for a, b in zip(cosine[:peak], cosine[1 : peak + 1], strict=True))  # warm-up rises
    assert all(a >= b for a, b in zip(cosine[peak:-1], cosine[peak + 1 :], strict=True))  # then decays
    assert learning_rate(1e-3, "cosine", 10.5, 20, warmup_epochs=1.0) == pytest.approx(5e-4)  # half-way: half
    # anneal: constant through the first 80 % of the run, then linear to zero
    assert learning_rate(1e-3, "anneal", 15.9, 20) == learning_rate(1e-3, "anneal", 16.0, 20) == 1e-3
    assert learning_rate(1e-3, "anneal", 18.0, 20) == pytest.approx(5e-4)
    assert learning_rate(1e-3, "anneal", 20.0, 20) == 0.0
    assert learning_rate(1e-3, "anneal", 0.5, 20, warmup_epochs=1.0) == pytest.approx(5e-4)


@pytest.mark.parametrize(("schedule", "shortest", "fixed"), [
    ("constant", 1, True), ("anneal", 2, True), ("anneal", 1, False), ("cosine", 40, False)])
def test_first_epoch_rate_is_fixed(schedule: str, shortest: int, fixed: bool) -> None:
    assert first_epoch_rate_is_fixed(schedule, shortest) is fixed
    rates = {learning_rate(1e-3, schedule, 0.99, epochs) for epochs in range(shortest, shortest + 30)}
    assert (len(rates) == 1) is fixed
