"""Counting a function's calls in a test: how often the trainer reads a checkpoint, a split or hull points."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest


def calls_of(monkeypatch: pytest.MonkeyPatch, owner: Any, name: str) -> list[tuple]:
    """The arguments of every call of ``owner.name`` from now on; the real function still runs."""
    real: Callable = getattr(owner, name)
    calls: list[tuple] = []

    def counting(*args: Any, **kwargs: Any) -> Any:
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(owner, name, counting)
    return calls
