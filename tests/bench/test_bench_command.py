"""The exit of ``python -m bench.<name>`` (and of experiments and tools): the main's status, or one line and status 2
for bad input."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from popcode_runtime.base.errors import PopcodeError
from tools.command import run_command
from tools.paths import ROOT


def _bad_input() -> int:
    raise PopcodeError("split.json: field 'scenes' is missing\n(a second line of advice)")


def test_bad_input_is_one_line_and_status_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as raised:
        run_command("bench.example", _bad_input)
    assert raised.value.code == 2
    assert capsys.readouterr().err == "bench.example: split.json: field 'scenes' is missing\n"


@pytest.mark.parametrize(("returned", "status"), [(3, 3), (0, 0), (None, 0), ({"records": []}, 0)])
def test_the_status_is_an_int_the_main_returns_else_0(returned: object, status: int) -> None:
    with pytest.raises(SystemExit) as raised:
        run_command("bench.example", lambda: returned)
    assert raised.value.code == status


def test_other_errors_keep_their_traceback() -> None:
    with pytest.raises(ZeroDivisionError):
        run_command("bench.example", lambda: 1 / 0)


def test_a_benchmark_given_a_missing_model_says_so_in_one_line(tmp_path: Path) -> None:
    missing = tmp_path / "missing.onnx"
    result = subprocess.run([sys.executable, "-m", "bench.agreement", str(missing), str(missing), "--split",
                             str(tmp_path), "--out", str(tmp_path / "out")], cwd=ROOT, capture_output=True,
                            text=True, timeout=300, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("bench.agreement: ") and result.stderr.count("\n") == 1, result.stderr
    assert str(missing) in result.stderr
    assert not (tmp_path / "out").exists()
