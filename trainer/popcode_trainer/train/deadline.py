"""A bound on how long a block of code may run, for work that can hang without raising (a compile, a fuzzed call)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def deadline(seconds: float, error: BaseException) -> Iterator[None]:
    """Raise ``error`` in the block once it has run ``seconds`` (> 0): a real-time alarm signal, which interrupts
    Python code and waits on child processes alike (not a C call that never returns to Python, nor work on other
    threads). Raise a ``BaseException`` that is not an ``Exception``, so that no library's ``except Exception``
    swallows or rewraps it.

    Only the main thread of a Unix process can take the signal; elsewhere, and inside a block already bounded by an
    alarm (a caller's own, or an outer deadline, which keeps its bound), the block runs without a bound of its own.
    An alarm that fires after the block has ended is ignored.
    """
    if not seconds > 0:
        raise ValueError(f"a deadline needs a positive number of seconds, got {seconds}")
    if (not hasattr(signal, "setitimer") or threading.current_thread() is not threading.main_thread()
            or signal.getitimer(signal.ITIMER_REAL)[0] > 0):
        yield
        return
    armed = True

    def expire(signum: int, frame: object) -> None:
        if armed:
            raise error

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        armed = False
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)
