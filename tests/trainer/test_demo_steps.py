"""The demo's steps at a tiny size: a model's training and export, the stage plan, the CLI's refusals and the
renders in processes."""

from __future__ import annotations

import dataclasses
import json
from functools import partial
from pathlib import Path

import numpy as np
import pytest
import torch
from calls import calls_of
from tiny_demo import TINY

from popcode_trainer.cli import main as cli_main
from popcode_trainer.data import hull
from popcode_trainer.data.render import render_builtin_split
from popcode_trainer.demo.parts import builtin_parts
from popcode_trainer.demo.plan import StagePlan
from popcode_trainer.demo.report import POPCODE
from popcode_trainer.demo.steps import in_processes, run_dir, train_and_export
from popcode_trainer.eval.reporting.overview_figures import nearest_equivalent
from popcode_trainer.train import training_data
from popcode_trainer.train.run_files import LAST_CHECKPOINT


def test_train_and_export_reads_its_checkpoint_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Training computes each object's hull points once and stores them; the export (calibration, parity, int8)
    reads the checkpoint it wrote once, and the split is read once for all of it."""
    split = render_builtin_split(tmp_path / "split", 4, obj_ids=[3, 6], random_position=True)
    loads, hulls = calls_of(monkeypatch, torch, "load"), calls_of(monkeypatch, hull, "hull_points_mm")
    splits = calls_of(monkeypatch, training_data, "read_bop_split")
    single_parts_only = dataclasses.replace(TINY, train_scenes=0, scene_share=0.0, detector_seconds=0.0)
    train_and_export(single_parts_only, POPCODE, [3, 6], split, tmp_path, ("int8",))
    assert [args[0] for args in loads] == [run_dir(tmp_path, POPCODE, [3, 6]) / LAST_CHECKPOINT]
    assert len(hulls) == 2
    assert [Path(args[0]) for args in splits] == [split]  # for training, parity crops and calibration alike


def test_stage_plan_rescales_what_is_left(capsys: pytest.CaptureFixture) -> None:
    plan = StagePlan([("a", 10.0), ("b", 30.0)])
    assert plan.remaining_s() == 40.0
    plan.done["a"] = 20.0  # twice as slow as estimated
    assert plan.scale == pytest.approx(2.0)
    assert plan.remaining_s() == pytest.approx(60.0)
    plan.revise({"a": 99.0, "b": 15.0})  # a finished step keeps its estimate
    assert plan.remaining_s() == pytest.approx(30.0)
    with plan.stage("b"):
        pass
    assert "[2/2] b: about 30 s; about 30 s left overall" in capsys.readouterr().out


def test_a_fixed_step_neither_sets_nor_takes_the_scale() -> None:
    """A step of given seconds (the detector's training) took them on a machine twice as fast as the estimates:
    the scale is the other steps' 0.5, not pulled towards 1, and a fixed step still to come keeps its seconds."""
    plan = StagePlan([("render", 100.0), ("detector", 150.0), ("score", 40.0), ("detector 2", 60.0)],
                     fixed=["detector", "detector 2"])
    plan.done.update({"render": 50.0, "detector": 150.0})
    assert plan.scale == pytest.approx(0.5)
    assert plan.remaining_s() == pytest.approx(0.5 * 40.0 + 60.0)


def test_nearest_equivalent_picks_the_symmetric_pose() -> None:
    flip = np.diag([-1.0, -1.0, 1.0])  # 180 deg about z
    info = {"symmetries_discrete": [np.pad(flip, ((0, 1), (0, 1))).ravel().tolist()]}
    info["symmetries_discrete"][0][-1] = 1.0
    R_true = np.eye(3)
    assert np.allclose(nearest_equivalent(R_true, flip, info), flip)
    assert np.allclose(nearest_equivalent(R_true, np.eye(3), info), np.eye(3))


def test_cli_refuses_zero_epochs(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    assert cli_main(["demo", "--out", str(tmp_path), "--epochs", "0"]) == 2
    assert "--epochs must be at least 1" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_cli_refuses_unknown_size(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["demo", "--out", str(tmp_path), "--size", "huge"])
    assert exit_info.value.code == 2
    assert "invalid choice: 'huge'" in capsys.readouterr().err


@pytest.mark.slow
def test_splits_rendered_in_processes_equal_one_process(tmp_path: Path) -> None:
    """The demo renders a large split's shards side by side; the split is the one a single process writes."""
    seed = TINY.config.train.seed
    parallel = in_processes(partial(builtin_parts().render_split, tmp_path / "parallel", 5, seed), False, 2)
    single = builtin_parts().render_split(tmp_path / "single", 5, seed, False)
    names = sorted(p.relative_to(parallel) for p in parallel.rglob("*") if p.is_file() and "records" not in p.parts)
    assert names == sorted(p.relative_to(single) for p in single.rglob("*")
                           if p.is_file() and "records" not in p.parts)
    for name in names:
        if name.suffix == ".json" and name.name != "popcode_render.json":
            assert json.loads((parallel / name).read_text()) == json.loads((single / name).read_text()), name
    assert len(list(parallel.glob("*/gray/*.png"))) == 6 * 5
