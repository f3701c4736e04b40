"""Epochs fitted to a time budget: the arithmetic, the fit file, and that a first epoch resumed to more
epochs trains exactly what one run of those epochs trains."""

from __future__ import annotations

import csv
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from popcode_runtime.base.errors import PopcodeError
from popcode_trainer.data.render import render_builtin_split
from popcode_trainer.demo import epoch_budget, run
from popcode_trainer.demo.group_codes import GroupCode
from popcode_trainer.demo.plan import SECONDS_PER_EXPORT, StagePlan
from popcode_trainer.demo.run import fit_epochs
from popcode_trainer.demo.sizes import DEMO_SIZES
from popcode_trainer.demo.steps import PipelineSize, run_dir, small_config, train_and_export, train_first_epoch
from popcode_trainer.train import fast_path, pretrained
from popcode_trainer.train.checkpoint import load
from popcode_trainer.train.network import NetworkConfig, build_network
from popcode_trainer.train.run_files import LAST_CHECKPOINT, METRICS_FILE

TINY = PipelineSize(8, 2, small_config(epochs=3, n_axes=42, n_angles=12, sigma_deg=30.0, batch_size=4,
                                       network=NetworkConfig(conv_channels=(4, 4, 4), squeeze_channels=2,
                                                             hidden=(16, 16, 16))),
                    ("population_code",))


@pytest.mark.parametrize(("epoch_s", "left_s", "bounds", "expected"), [
    (10.0, 95.0, (1, 100), 10),  # the first epoch and 9 more
    (10.0, 95.0, (1, 5), 5),  # capped
    (10.0, -30.0, (3, 100), 3),  # nothing left: the lowest
    (10.0, -30.0, (1, 100), 1),
])
def test_fitted_epochs(epoch_s: float, left_s: float, bounds: tuple[int, int], expected: int) -> None:
    assert epoch_budget.fitted_epochs(epoch_s, left_s, bounds) == expected


@pytest.mark.parametrize(("epoch_s", "bounds", "message"), [
    (0.0, (1, 5), "must take some time"), (float("nan"), (1, 5), "must take some time"),
    (1.0, (0, 5), "1 <= lowest <= highest"), (1.0, (6, 5), "1 <= lowest <= highest")])
def test_fitted_epochs_refuses_nonsense(epoch_s: float, bounds: tuple[int, int], message: str) -> None:
    with pytest.raises(PopcodeError, match=message):
        epoch_budget.fitted_epochs(epoch_s, 10.0, bounds)


def test_fit_file_round_trip_and_bad_file(tmp_path: Path) -> None:
    assert epoch_budget.load(tmp_path) is None
    fit = epoch_budget.fit({"a": 4.0, "b": 6.0}, 600.0, 101.0, (2, 50))
    assert fit.epochs == 11
    epoch_budget.save(fit, tmp_path)
    assert epoch_budget.load(tmp_path) == fit
    (tmp_path / epoch_budget.FIT_FILE).write_text('{"epochs": 3}')
    with pytest.raises(PopcodeError, match="not an epoch fit"):
        epoch_budget.load(tmp_path)


def test_a_folder_fitted_for_other_models_is_refused_not_resumed(tmp_path: Path) -> None:
    """A run folder's fit names its models; a resume whose parts now group otherwise (a newer version splits them
    by code) is refused in one line instead of failing on a model the fit never timed."""
    demo = DEMO_SIZES["quick"]
    size, code = demo.pipeline, demo.pipeline.config.code
    pooled = {run_dir(tmp_path, r, (1, 2)).name: 10.0 for r in size.representations}
    epoch_budget.save(epoch_budget.EpochFit(5, 720.0, 600.0, pooled, (4, 40)), tmp_path)
    same = [GroupCode((1, 2), code, 20.0, "")]
    assert fit_epochs(size, demo, same, tmp_path, tmp_path, 0.0, None).epochs == 5  # kept: nothing is run
    split = [GroupCode((1,), code, 20.0, ""), GroupCode((2,), code, 20.0, "")]
    with pytest.raises(PopcodeError, match=r"was started with other models \(population_code_1-2, single_var.*"
                                           r"now population_code_1, population_code_2, .*use another --out"):
        fit_epochs(size, demo, split, tmp_path, tmp_path, 0.0, None)


def test_a_compile_is_paid_once_not_per_epoch(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A first epoch that compiled the step: its compile is left out of an epoch's cost (the resume, in the same
    process, finds the compile caches warm); metrics of an older trainer have no compile."""
    demo = replace(DEMO_SIZES["quick"], minutes=10.0, epoch_bounds=(4, 1000), fine_tune_epoch_bounds=None)
    size = replace(demo.pipeline, representations=("population_code",))
    groups = [GroupCode((1, 2), size.config.code, 20.0, "")]

    def compiled_first_epoch(size, representation, obj_ids, split, out_dir, code=None) -> float:
        folder = run_dir(out_dir, representation, obj_ids)
        folder.mkdir(parents=True)
        (folder / METRICS_FILE).write_text("epoch,seconds,compile_seconds\n1,50.0,40.0\n")
        return epoch_budget.first_epoch_seconds(folder)

    monkeypatch.setattr(run, "train_first_epoch", compiled_first_epoch)
    fit = fit_epochs(size, demo, groups, tmp_path, tmp_path / "out", time.perf_counter(), StagePlan([]))
    assert fit.first_epoch_seconds == {"population_code_1-2": 10.0}
    assert fit.seconds_left == pytest.approx(600.0 - SECONDS_PER_EXPORT, abs=1.0)
    assert fit.epochs == 1 + int(fit.seconds_left // 10.0)  # epochs of 10 s, not of 50
    older = tmp_path / "older"
    older.mkdir()
    (older / METRICS_FILE).write_text("epoch,seconds\n1,50.0\n")
    assert epoch_budget.first_epoch_seconds(older) == 50.0 and epoch_budget.first_epoch_compile_seconds(older) == 0


def test_the_resume_keeps_the_first_epochs_choice_to_compile(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """"auto" weighs a compile against the run's length, which the fit changes; the fit reserved the first epoch's
    compile (or none), so the resume must not decide otherwise."""
    split = render_builtin_split(tmp_path / "split", images_per_object=TINY.train_images_per_object, obj_ids=[3, 4])
    train_first_epoch(TINY.with_epochs(7), "population_code", [3, 4], split, tmp_path)  # short: eager
    folder = run_dir(tmp_path, "population_code", [3, 4])
    assert not load(folder / LAST_CHECKPOINT)["step_path"]["compiled"]
    monkeypatch.setattr(fast_path, "COMPILE_MIN_STEPS", 1)  # "auto" would now compile this run...
    monkeypatch.setattr(fast_path, "cpu_flags", lambda: frozenset({"amx_bf16"}))
    assert fast_path.choose_path("auto", "auto", torch.device("cpu"), 10).compiled
    train_and_export(TINY, "population_code", [3, 4], split, tmp_path)  # ...but the resume keeps eager
    state = load(folder / LAST_CHECKPOINT)
    assert state["epoch"] == TINY.config.train.epochs and not state["step_path"]["compiled"]
    assert state["config"]["train"]["compile"] == "off"


def test_first_epoch_seconds_names_a_run_without_epochs(tmp_path: Path) -> None:
    with pytest.raises(PopcodeError, match="no first epoch to time"):
        epoch_budget.first_epoch_seconds(tmp_path)
    (tmp_path / METRICS_FILE).write_text("epoch,seconds\n")
    with pytest.raises(PopcodeError, match="no first epoch to time"):
        epoch_budget.first_epoch_seconds(tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize(("schedule", "equal"), [("constant", True), ("anneal", True), ("cosine", False)])
def test_first_epoch_resumed_equals_one_run(tmp_path: Path, schedule: str, equal: bool) -> None:
    """The first epoch trained as part of a longer nominal run (7 epochs), then resumed to 3, equals 3 in one go
    unless the schedule's first epoch depends on the run's length (cosine)."""
    tiny = replace(TINY, config=replace(TINY.config, train=replace(TINY.config.train, schedule=schedule)))
    split = render_builtin_split(tmp_path / "split", images_per_object=TINY.train_images_per_object, obj_ids=[3, 4])
    fitted = run_dir(tmp_path / "fitted", "population_code", [3, 4])
    wall = train_first_epoch(tiny.with_epochs(7), "population_code", [3, 4], split, tmp_path / "fitted")
    assert wall > epoch_budget.first_epoch_seconds(fitted) > 0  # the wall time holds validation and checkpoint
    before = (fitted / LAST_CHECKPOINT).stat().st_mtime_ns
    again = train_first_epoch(tiny.with_epochs(7), "population_code", [3, 4], split, tmp_path / "fitted")
    assert again == epoch_budget.first_epoch_seconds(fitted)
    assert (fitted / LAST_CHECKPOINT).stat().st_mtime_ns == before  # kept, not trained again
    train_and_export(tiny, "population_code", [3, 4], split, tmp_path / "fitted")
    train_and_export(tiny, "population_code", [3, 4], split, tmp_path / "straight")
    straight = run_dir(tmp_path / "straight", "population_code", [3, 4])

    resumed, direct = load(fitted / LAST_CHECKPOINT), load(straight / LAST_CHECKPOINT)
    assert resumed["epoch"] == direct["epoch"] == TINY.config.train.epochs
    same = [torch.equal(resumed["model"][name], tensor) for name, tensor in direct["model"].items()]
    assert all(same) if equal else not all(same)
    with open(fitted / METRICS_FILE, newline="") as handle:
        assert [int(row["epoch"]) for row in csv.DictReader(handle)] == [1, 2, 3]


def test_a_fine_tune_from_the_shipped_start_may_fit_fewer_epochs(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The quick size's floor is lower where its models take a pretrained start (they converge faster); without one
    (none shipped for the network, or --from-scratch) the size's own bounds hold."""
    demo = DEMO_SIZES["quick"]
    assert demo.fine_tune_epoch_bounds is not None and demo.fine_tune_epoch_bounds[0] < demo.epoch_bounds[0]
    monkeypatch.setattr(pretrained, "SHIPPED_DIR", tmp_path)  # nothing shipped here
    assert run.epoch_bounds(demo, demo.pipeline) == demo.epoch_bounds
    network = replace(demo.pipeline.config.network, input_size=demo.pipeline.config.data.crop_size)
    pretrained.write_start(build_network(network), network, pretrained.shipped_path(network), {"parts": 1})
    assert run.epoch_bounds(demo, demo.pipeline) == demo.fine_tune_epoch_bounds
    assert run.epoch_bounds(demo, demo.pipeline.with_init("none")) == demo.epoch_bounds
