"""experiments/shipped_variants.sh: one render, several networks trained side by side, each one's model and every log
brought back; a wrong call is refused before anything runs."""

from __future__ import annotations

import os
import subprocess
import sys
import tarfile
from pathlib import Path

import onnx
import pytest

from tools.paths import ROOT

SCRIPT = ROOT / "experiments" / "shipped_variants.sh"


def _run(*args: str | Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"  # python3 is this interpreter
    return subprocess.run(["bash", str(SCRIPT), *map(str, args)], cwd=ROOT, capture_output=True, text=True,
                          timeout=600, env={**os.environ, "PATH": path, **(env or {})})


@pytest.mark.slow
def test_each_network_trains_from_one_render_and_comes_back(tmp_path: Path) -> None:
    results = tmp_path / "results"
    done = _run(tmp_path / "work", results, 120, "tiny", "small",
                env={"SHIPPED_ARGS": "--images 6 --scenes 4 --test-images 1 --group 3", "PYOPENGL_PLATFORM": "egl"})
    assert done.returncode == 0, done.stdout + done.stderr
    assert sorted(path.name for path in results.iterdir()) == ["logs.tgz", "small.onnx", "tiny.onnx"]
    widths = {name: [init.dims[0] for init in onnx.load(str(results / f"{name}.onnx")).graph.initializer
                     if len(init.dims) == 4] for name in ("tiny", "small")}
    assert max(widths["tiny"]) < max(widths["small"])  # each network is its own
    assert (tmp_path / "work" / "tiny" / "train").resolve() == (tmp_path / "work" / "data" / "train").resolve()
    with tarfile.open(results / "logs.tgz") as logs:
        names = set(logs.getnames())
    assert {"./render.log", "./tiny.log", "./small.log", "copy/tiny/run.json", "copy/small/run.json"} <= names
    assert not any(name.endswith(".onnx") for name in names)
    assert "tiny: " in done.stdout and "small: " in done.stdout  # each network's epochs line


def test_too_few_arguments_exit_2_and_write_nothing(tmp_path: Path) -> None:
    refused = _run(tmp_path / "work", tmp_path / "results", 120)
    assert refused.returncode == 2 and "usage" in refused.stderr
    assert list(tmp_path.iterdir()) == []
