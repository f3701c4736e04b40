"""One writer per output: an exclusive lock file beside what a command writes.

POSIX ``flock`` on ``<name>.lock``: the system drops the lock when the process
ends, a ``kill -9`` too, so a lock left by a killed run never blocks the next
one. Of two commands writing one output, the second is refused in one line.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from .errors import PopcodeError

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]

MAX_OPEN_TRIES = 100  # each retry follows a release by another writer: more in a row means a storm, not a race


class OutputLock:
    """An exclusive lock on ``path`` held until :meth:`release`; ``busy`` says in the refusal what holds it and
    what to do (for example "another popcode detect or run is writing results.csv ... choose another --out").
    Taken when made; as a context manager, released when the block ends, however it ends."""

    def __init__(self, path: Path, busy: str) -> None:
        self.path, self._handle = path, None
        if fcntl is None:  # no flock (Windows): writers are not guarded against each other
            return
        if path.exists() and not path.is_file():  # opening a FIFO would wait for a reader forever
            raise PopcodeError(f"{path} is not a regular file; remove it (it is where the lock is kept)")
        for _ in range(MAX_OPEN_TRIES):
            handle = path.open("a")
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as error:
                handle.close()
                raise PopcodeError(busy) from error
            if _same_file(handle, path):
                self._handle = handle
                return
            handle.close()  # a holder released (and removed) the file between our open and our lock: open anew
        raise PopcodeError(busy)

    def __enter__(self) -> OutputLock:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.release()

    def release(self) -> None:
        if self._handle is not None:
            self.path.unlink(missing_ok=True)  # while still held: a writer that opens it later locks a new file
            self._handle.close()
            self._handle = None


def _same_file(handle: IO[str], path: Path) -> bool:
    """Whether ``handle`` is still the file at ``path``: a releasing holder removes the file while it holds it, so a
    lock taken on the removed file guards nothing."""
    try:
        return os.fstat(handle.fileno()).st_ino == path.stat().st_ino
    except FileNotFoundError:
        return False


@contextmanager
def folder_lock(folder: Path, name: str, busy: str) -> Iterator[None]:
    """Hold the lock ``folder/name`` (the folder made if missing) while the block writes into the folder; a block
    that fails (a refused input, say) leaves no empty folder of its own making behind."""
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    try:
        with OutputLock(folder / name, busy):
            yield
    except BaseException:
        if made and not any(folder.iterdir()):
            folder.rmdir()
        raise
