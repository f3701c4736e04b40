"""Runs in other processes: two CPU ranks under torchrun (gloo), and a run killed with SIGKILL then resumed."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from popcode_trainer.train import checkpoint
from popcode_trainer.train.run_files import LAST_CHECKPOINT, METRICS_FILE

HERE = Path(__file__).parent
ROOT = HERE.parents[1]
ENV = {**os.environ, "OMP_NUM_THREADS": "1",
       "PYTHONPATH": os.pathsep.join(str(ROOT / p) for p in ("runtime", "trainer", "tests", "tests/trainer"))}


@pytest.mark.slow
def test_two_process_torchrun(tmp_path: Path) -> None:
    torchrun = shutil.which("torchrun", path=str(Path(sys.executable).parent)) or shutil.which("torchrun")
    assert torchrun, "torchrun is installed with torch"
    result = subprocess.run(
        [torchrun, "--standalone", "--nproc_per_node=2", str(HERE / "ddp_train.py"), str(tmp_path), "2"],
        env=ENV, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    state = checkpoint.load(tmp_path / LAST_CHECKPOINT)
    assert state["epoch"] == 2
    lines = (tmp_path / METRICS_FILE).read_text().splitlines()
    assert len(lines) == 3  # header + 2 epochs: one writer


@pytest.mark.slow
def test_killed_run_resumes_to_the_uninterrupted_state(tmp_path: Path) -> None:
    script = [sys.executable, str(HERE / "ddp_train.py")]
    epochs = "6"
    subprocess.run([*script, str(tmp_path / "straight"), epochs], env=ENV, check=True, capture_output=True,
                   timeout=300)

    killed = tmp_path / "killed"
    process = subprocess.Popen([*script, str(killed), epochs], env=ENV, stdout=subprocess.DEVNULL,
                               stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 240
    while not (killed / LAST_CHECKPOINT).exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    process.send_signal(signal.SIGKILL)
    assert process.wait(timeout=60) == -signal.SIGKILL, "the run ended before it could be killed"
    stopped_at = checkpoint.load(killed / LAST_CHECKPOINT)["epoch"]
    assert 1 <= stopped_at < 6

    subprocess.run([*script, str(killed), epochs, "--resume"], env=ENV, check=True, capture_output=True,
                   timeout=300)
    a = checkpoint.load(tmp_path / "straight" / LAST_CHECKPOINT)
    b = checkpoint.load(killed / LAST_CHECKPOINT)
    assert a["epoch"] == b["epoch"] == 6
    for key, tensor in a["model"].items():
        assert torch.equal(tensor, b["model"][key]), key
    rows = (killed / METRICS_FILE).read_text().splitlines()[1:]
    assert [int(row.split(",")[0]) for row in rows] == [1, 2, 3, 4, 5, 6]
