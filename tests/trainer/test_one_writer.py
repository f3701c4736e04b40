"""Issue 50: one writer per output for every long ``popcode-train`` command. A second one on the same output is
refused in one line that names the output and an option of the command, and a lock file a killed run left (no
process holds it) blocks nothing."""

from __future__ import annotations

import argparse
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest
from hostile_cases import error_lines
from tiny import tiny_config, tiny_data, tiny_representation

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.output_lock import OutputLock
from popcode_trainer.cli import build_parser, main
from popcode_trainer.commands.evaluate import EVALUATE_LOCK
from popcode_trainer.demo.run import DEMO_LOCK
from popcode_trainer.kit.run import KIT_LOCK
from popcode_trainer.train.loop import train
from popcode_trainer.train.run_files import RUN_LOCK
from tools.paths import ROOT, SHIPPED_1_2

WORK_BEGAN = "the long work began"  # what the stubbed first step of each command says: the lock let it through
ENV = {**os.environ, "OMP_NUM_THREADS": "1",
       "PYTHONPATH": os.pathsep.join(str(ROOT / p) for p in ("runtime", "trainer"))}


@dataclass(frozen=True)
class Writer:
    """A long command writing under a test's folder, the lock file a running one holds, and its first long step."""

    argv: Callable[[Path], list[str]]
    lock: Callable[[Path], Path]
    work: str  # the first long step, stubbed to raise WORK_BEGAN
    named: Callable[[Path], tuple[str, ...]]  # what the refusal names: the output, an option of the command, ...
    checks: tuple[str, ...] = ()  # the checks of its input before it, stubbed to pass


WRITERS = {
    "render": Writer(lambda d: ["render", "--objects", "builtin", "--images", "1", "--shard", "1/2", "--out",
                                str(d / "split")],
                     lambda d: d / "split" / ".render-1-of-2.lock",
                     "popcode_trainer.commands.render.write_builtin_models",
                     lambda d: (f"shard 1/2 of {d / 'split'}", "--shard", "--out")),
    "train": Writer(lambda d: ["train", "--set", f'train.out_dir="{d / "run"}"'],
                    lambda d: d / "run" / RUN_LOCK,
                    "popcode_trainer.train.training_data.build_training_data",
                    lambda d: (str(d / "run"), "--set", "train.out_dir"),
                    ("popcode_trainer.train.training_data.read_training_split",)),
    "export": Writer(lambda d: ["export", str(d / "last.pt"), "--out", str(d / "model.onnx")],
                     lambda d: d / "model.onnx.lock",
                     "popcode_trainer.train.checkpoint.load_trained",
                     lambda d: (str(d / "model.onnx"), "--out")),
    "evaluate": Writer(lambda d: ["evaluate", str(SHIPPED_1_2), "--split", str(d / "split"), "--models-dir",
                                  str(d / "models"), "--out", str(d / "eval")],
                       lambda d: d / "eval" / EVALUATE_LOCK,
                       "popcode_trainer.commands.evaluate.read_eval_split",
                       lambda d: (str(d / "eval"), "--out")),
    "demo": Writer(lambda d: ["demo", "--size", "smoke", "--out", str(d / "demo")],
                   lambda d: d / "demo" / DEMO_LOCK,
                   "popcode_trainer.demo.run.render_splits",
                   lambda d: (str(d / "demo"), "--out")),
    "kit": Writer(lambda d: ["kit", "--objects", "builtin", "--out", str(d / "kit"), "--hours", "1", "--size", "smoke"],
                  lambda d: d / "kit" / KIT_LOCK,
                  "popcode_trainer.kit.run.run_demo",
                  lambda d: (str(d / "kit"), "--out")),
}


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    """Where the commands write; with the (empty) split and models folders evaluate is pointed at."""
    (tmp_path / "split").mkdir()
    (tmp_path / "models").mkdir()
    return tmp_path


def _stub_work(monkeypatch: pytest.MonkeyPatch, writer: Writer) -> None:
    def work(*args: object, **kwargs: object) -> None:
        raise PopcodeError(WORK_BEGAN)

    monkeypatch.setattr(writer.work, work)
    for check in writer.checks:
        monkeypatch.setattr(check, lambda *args, **kwargs: None)


def _options(command: str) -> set[str]:
    """The options the command's parser has."""
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    return {option for action in commands.choices[command]._actions for option in action.option_strings}


def _held(lock: Path) -> OutputLock:
    """``lock`` held as a running command holds it; flock locks belong to an open file, so a second open in this
    same process is refused as another process's would be."""
    lock.parent.mkdir(parents=True, exist_ok=True)
    held = OutputLock(lock, "held by the test")
    with pytest.raises(PopcodeError, match="held by the test"):
        OutputLock(lock, "held by the test")
    return held


@pytest.mark.parametrize("command", WRITERS)
def test_a_second_writer_is_refused_in_one_line(command: str, folder: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    writer = WRITERS[command]
    _stub_work(monkeypatch, writer)
    with _held(writer.lock(folder)):
        assert main(writer.argv(folder)) == 2
        lines = error_lines(capsys.readouterr().err)
        assert len(lines) == 1 and lines[0].startswith("popcode-train: error: another "), lines
        assert all(name in lines[0] for name in writer.named(folder)), lines[0]
        assert writer.named(folder)[1] in _options(command)
        assert writer.lock(folder).exists()  # the running command's lock is left alone


@pytest.mark.parametrize("command", WRITERS)
def test_a_lock_left_by_a_killed_run_blocks_nothing(command: str, folder: Path, monkeypatch: pytest.MonkeyPatch,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    writer = WRITERS[command]
    _stub_work(monkeypatch, writer)
    lock = writer.lock(folder)
    lock.parent.mkdir(parents=True, exist_ok=True)
    lock.touch()  # what a kill -9 leaves: the file, and no process holding it
    assert main(writer.argv(folder)) == 2
    assert error_lines(capsys.readouterr().err) == [f"popcode-train: error: {WORK_BEGAN}"]
    assert not lock.exists()  # taken, then released on the way out, an error's way too


def test_under_torchrun_only_rank_0_holds_the_run_folder(folder: Path, monkeypatch: pytest.MonkeyPatch,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """The other ranks write nothing there, and must not be refused by their own rank 0's lock."""
    writer = WRITERS["train"]
    _stub_work(monkeypatch, writer)
    with _held(writer.lock(folder)):
        for rank, refused in (("1", False), ("0", True)):
            monkeypatch.setenv("RANK", rank)
            assert main(writer.argv(folder)) == 2
            (line,) = error_lines(capsys.readouterr().err)
            assert (WORK_BEGAN not in line) == refused, (rank, line)


def test_shards_of_one_split_render_side_by_side(folder: Path, monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """One lock per shard: another shard's lock (held, in a split with nothing else yet) lets this one through."""
    writer = WRITERS["render"]
    _stub_work(monkeypatch, writer)
    with _held(folder / "split" / ".render-0-of-2.lock"):
        assert main(writer.argv(folder)) == 2
    assert error_lines(capsys.readouterr().err) == [f"popcode-train: error: {WORK_BEGAN}"]


def test_the_training_loop_holds_its_run_folder(tmp_path: Path) -> None:
    """The loop (the demo trains through it) is refused while its folder is held, and a run's folder that holds a
    run names the train command's options."""
    config = tiny_config(tmp_path / "run", epochs=1)
    representation = tiny_representation(config)
    train_set, _ = tiny_data(representation, val_count=0)
    busy = (r"another process is training into .*run \(it holds train.lock\); wait for it to end, or train into "
            r"another folder \(train: --set train.out_dir=DIR; demo: another --out\)")
    with _held(tmp_path / "run" / RUN_LOCK), pytest.raises(PopcodeError, match=busy):
        train(config, representation, train_set)
    train(config, representation, train_set)
    assert not (tmp_path / "run" / RUN_LOCK).exists()
    with pytest.raises(PopcodeError, match=r"already holds a run; continue it with train --resume, or train into "
                                           r"another folder \(--set train.out_dir=DIR\)"):
        train(config, representation, train_set)


@pytest.mark.slow
def test_a_second_demo_on_one_out_is_refused_while_the_first_runs(tmp_path: Path) -> None:
    """Two real processes at the smoke size: the second is refused, the first killed, and its lock file holds
    nobody back. The first is stopped once it renders, holding its lock, so that it does not render and train on
    the CPU the second needs."""
    out = tmp_path / "demo"
    command = [sys.executable, "-m", "popcode_trainer.cli", "demo", "--size", "smoke", "--out", str(out)]
    first = subprocess.Popen(command, env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        while not (out / "train").exists():  # rendering began
            assert first.poll() is None, "the first demo ended before it rendered"
            time.sleep(0.05)
        first.send_signal(signal.SIGSTOP)
        second = subprocess.run(command, env=ENV, capture_output=True, text=True, timeout=600)
    finally:
        first.kill()
        first.wait()
    assert second.returncode == 2 and error_lines(second.stderr) == [
        f"popcode-train: error: another popcode-train demo is writing {out} (it holds {DEMO_LOCK}); wait for it to "
        "end, or give another --out"], second.stderr
    assert (out / DEMO_LOCK).exists()  # left by the killed demo, and held by nobody: a rerun resumes
    OutputLock(out / DEMO_LOCK, "a killed demo's lock is still held").release()
