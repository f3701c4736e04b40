"""The one deadline: raises in the block once it has run its seconds, keeps an outer bound, leaves no alarm behind."""

from __future__ import annotations

import signal
import time

import pytest

from popcode_trainer.train.deadline import deadline


class Outer(BaseException):
    pass


class Inner(BaseException):
    pass


def test_a_block_past_its_deadline_is_interrupted_and_the_alarm_is_restored() -> None:
    before = signal.getsignal(signal.SIGALRM)
    with pytest.raises(Inner), deadline(0.05, Inner()):
        time.sleep(30)  # never ends without the alarm: the test would hang, not pass
    assert signal.getitimer(signal.ITIMER_REAL)[0] == 0.0 and signal.getsignal(signal.SIGALRM) is before
    with deadline(5.0, Inner()):
        pass  # ends in time: nothing raised, no alarm left
    assert signal.getitimer(signal.ITIMER_REAL)[0] == 0.0


def test_an_outer_deadline_keeps_its_bound() -> None:
    """An inner deadline inside an armed one does not cancel it (it runs without a bound of its own)."""
    with pytest.raises(Outer), deadline(0.1, Outer()), deadline(0.02, Inner()):
        time.sleep(30)


def test_a_deadline_needs_positive_seconds() -> None:
    with pytest.raises(ValueError, match="positive number of seconds"), deadline(0.0, Inner()):
        pass
