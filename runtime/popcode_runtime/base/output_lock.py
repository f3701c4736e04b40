"""One writer per output: an exclusive lock file beside what a command writes.

POSIX ``flock`` on ``<name>.lock``: the system drops the lock when the process
ends, a ``kill -9`` too, so a lock left by a killed run never blocks the next
one. Of two commands writing one output, the second is refused in one line.
"""

from __future__ import annotations

from pathlib import Path

from .errors import PopcodeError

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]


class OutputLock:
    """An exclusive lock on ``path`` held until :meth:`release`; ``busy`` says in the refusal what holds it and
    what to do (for example "another popcode run is writing results.csv ... choose another --out")."""

    def __init__(self, path: Path, busy: str) -> None:
        self.path, self._handle = path, None
        if fcntl is None:  # no flock (Windows): writers are not guarded against each other
            return
        if path.exists() and not path.is_file():  # opening a FIFO would wait for a reader forever
            raise PopcodeError(f"{path} is not a regular file; remove it (it is where the lock is kept)")
        handle = path.open("a")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            handle.close()
            raise PopcodeError(busy) from error
        self._handle = handle

    def release(self) -> None:
        if self._handle is not None:
            self.path.unlink(missing_ok=True)  # while still held: a writer that opens it later locks a new file
            self._handle.close()
            self._handle = None
