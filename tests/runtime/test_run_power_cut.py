"""``popcode run``'s results survive a power cut, not only a killed process (issue 66): every file is synced before
its rename and its folder after it (``power_cut``), and a failed write leaves what was there."""

from __future__ import annotations

from pathlib import Path

import pytest
from power_cut import PowerCut

from popcode_runtime.base.files import SyncBatch, atomic_path, write_bytes_atomic
from popcode_runtime.commands.cli import main
from popcode_trainer.data.render import render_builtin_split

MODELS = Path(__file__).resolve().parents[2] / "models"
SHIPPED = [str(MODELS / "builtin-parts-1-2.onnx"), str(MODELS / "builtin-parts-3-6.onnx")]


def test_the_results_of_a_run_survive_a_power_cut(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    split = render_builtin_split(tmp_path / "split", 1, size=(160, 120), random_position=True)
    out = tmp_path / "out" / "results.csv"
    out.parent.mkdir()
    cut = PowerCut().install(monkeypatch)
    assert main(["run", *SHIPPED, "--split", str(split), "--out", str(out), "--quiet", "--gt-boxes"]) == 0
    assert cut.survivor(out) == out.read_bytes(), "the results are lost or empty after a power cut"
    assert out.read_text().count("\n") > 1  # the header and estimates
    assert cut.unsafe_renames() == []


def test_a_write_that_fails_leaves_the_old_file_and_no_temporary(tmp_path: Path) -> None:
    path = tmp_path / "model.onnx"
    write_bytes_atomic(path, b"old")
    with pytest.raises(RuntimeError), atomic_path(path) as temporary:
        temporary.write_bytes(b"half")
        raise RuntimeError("the writer failed")
    assert path.read_bytes() == b"old" and [p.name for p in tmp_path.iterdir()] == [path.name]


@pytest.mark.parametrize("syncfs", [True, False], ids=["syncfs", "fsync-each-file"])
def test_a_sync_batch_makes_its_files_durable_only_at_its_commit(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                 syncfs: bool) -> None:
    cut = PowerCut().install(monkeypatch, syncfs=syncfs)
    batch = SyncBatch()
    paths = [tmp_path / "a" / "one.png", tmp_path / "b" / "two.png"]
    for path in paths:
        path.parent.mkdir()
        write_bytes_atomic(path, path.name.encode(), batch)
    assert [cut.survivor(path) for path in paths] == [None, None]
    assert [cut.survivor(path, journal_committed=True) for path in paths] == [b"", b""]  # renamed, data not synced
    batch.commit()
    assert [cut.survivor(path) for path in paths] == [b"one.png", b"two.png"]
