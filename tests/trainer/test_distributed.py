"""Two CPU processes under torchrun (gloo): the run completes and only rank 0 writes."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from popcode_trainer import checkpoint
from popcode_trainer.train import METRICS_FILE

HERE = Path(__file__).parent


@pytest.mark.slow
def test_two_process_torchrun(tmp_path: Path) -> None:
    torchrun = shutil.which("torchrun", path=str(Path(sys.executable).parent)) or shutil.which("torchrun")
    assert torchrun, "torchrun is installed with torch"
    root = HERE.parents[1]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(root / p) for p in ("runtime", "trainer", "tests",
                                                                              "tests/trainer")),
           "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [torchrun, "--standalone", "--nproc_per_node=2", str(HERE / "ddp_train.py"), str(tmp_path)],
        env=env, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    state = checkpoint.load(tmp_path / checkpoint.LAST)
    assert state["epoch"] == 2
    lines = (tmp_path / METRICS_FILE).read_text().splitlines()
    assert len(lines) == 3  # header + 2 epochs: one writer
