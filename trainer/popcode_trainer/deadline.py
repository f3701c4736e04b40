"""A bound on how long a block of code may run, for work that can hang without raising (a compile, a fuzzed call)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def deadline(seconds: float, error: BaseException) -> Iterator[None]:
    """Raise ``error`` in the block once it has run ``seconds``: a real-time alarm signal, which interrupts Python
    code and waits on child processes alike (not a C call that never returns to Python). Only the main thread of a
    Unix process can take the signal; elsewhere the block runs unbounded."""
    if not hasattr(signal, "setitimer") or threading.current_thread() is not threading.main_thread():
        yield
        return

    def expire(signum: int, frame: object) -> None:
        raise error

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)
