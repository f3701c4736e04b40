"""A full disk, a read-only folder or a name too long end in one line naming the file, and nothing written so
far is lost (issue 30)."""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import IO

import pytest

import popcode_runtime.commands.run_results as run_results
from popcode_runtime.commands.cli import main
from popcode_trainer.data.render import render_builtin_split

MODELS = Path(__file__).resolve().parents[2] / "models"
SHIPPED = [str(MODELS / "builtin-parts-1-2.onnx"), str(MODELS / "builtin-parts-3-6.onnx")]


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return render_builtin_split(tmp_path_factory.mktemp("full") / "split", 1, size=(160, 120), random_position=True)


def _run(split: Path, out: Path) -> int:
    return main(["run", *SHIPPED, "--split", str(split), "--out", str(out), "--quiet", "--gt-boxes"])


def test_a_full_disk_mid_run_is_one_line_and_keeps_the_finished_images(split: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "results.csv"
    partial = out.with_name("results.csv.partial")
    real_flush, calls = run_results.flush_to_disk, {"n": 0}

    def disk_full_at_the_third_image(handle: IO) -> None:
        calls["n"] += 1
        if calls["n"] == 3:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(partial))
        real_flush(handle)

    monkeypatch.setattr(run_results, "flush_to_disk", disk_full_at_the_third_image)
    assert _run(split, out) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(partial) in err and os.strerror(errno.ENOSPC) in err
    kept = partial.read_text().count("#done")
    assert kept >= 2 and not out.exists()
    monkeypatch.undo()
    assert _run(split, out) == 0  # room again: the same command finishes the run
    assert f"({kept} done by an earlier run)" in capsys.readouterr().out and not partial.exists()


@pytest.mark.parametrize("command", ["run", "predict-draw"])
def test_an_output_name_too_long_is_refused_before_any_work(split: Path, tmp_path: Path, command: str,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    name = "r" * 240
    if command == "run":
        code = _run(split, tmp_path / f"{name}.csv")
    else:
        image = next((split / "000003" / "gray").iterdir())
        code = main(["predict", SHIPPED[1], str(image), "--box", "10,10,40,40", "--obj-id", "3",
                     "--draw", str(tmp_path / f"{name}.png")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "bytes; at most 200" in err
    assert not list(tmp_path.iterdir())
