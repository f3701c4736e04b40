"""One writer per output: the lock refuses a second writer and never guards a file its holder has removed."""

from __future__ import annotations

from pathlib import Path

import pytest

from popcode_runtime.base import output_lock
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.output_lock import OutputLock, folder_lock


def test_a_second_writer_is_refused_until_the_first_releases(tmp_path: Path) -> None:
    path = tmp_path / "out.lock"
    with OutputLock(path, "another writer holds out.lock"), \
            pytest.raises(PopcodeError, match="another writer holds out.lock"):
        OutputLock(path, "another writer holds out.lock")
    assert not path.exists()
    OutputLock(path, "busy").release()


def test_a_lock_on_the_file_its_holder_just_removed_is_taken_anew(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    # The holder ends between a second writer's open and its lock: that lock would be on a removed file, and a
    # third writer, opening the path anew, would lock another file and write beside it.
    path = tmp_path / "out.lock"
    holder = OutputLock(path, "busy")
    real_flock, opened = output_lock.fcntl.flock, []

    def release_before_the_first_lock(handle, flags):
        opened.append(handle)
        if len(opened) == 1:
            holder.release()
        return real_flock(handle, flags)

    monkeypatch.setattr(output_lock.fcntl, "flock", release_before_the_first_lock)
    taken = OutputLock(path, "busy")
    monkeypatch.undo()
    assert len(opened) == 2 and path.is_file()
    with pytest.raises(PopcodeError, match="busy"):
        OutputLock(path, "busy")
    taken.release()


def test_a_failed_block_leaves_no_folder_it_made(tmp_path: Path) -> None:
    made, kept = tmp_path / "new", tmp_path / "old"
    kept.mkdir()
    for folder in (made, kept):
        with pytest.raises(PopcodeError, match="refused"), folder_lock(folder, "x.lock", "busy"):
            raise PopcodeError("refused")
    assert not made.exists() and kept.is_dir() and not any(kept.iterdir())
    with folder_lock(made, "x.lock", "busy"):
        (made / "report.md").write_text("done")
    assert [p.name for p in made.iterdir()] == ["report.md"]
