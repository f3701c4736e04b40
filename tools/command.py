"""The exit of ``python -m bench.<name>``, ``experiments.<name>`` or ``tools.<name>`` (no torch here: some need the
runtime only)."""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NoReturn

from popcode_runtime.base.errors import PopcodeError, first_line


@contextmanager
def bad_input_exits(command: str) -> Iterator[None]:
    """Bad input (a ``PopcodeError``) becomes one line ``<command>: why`` (``command``: the module as run, e.g.
    ``bench.latency``) and status 2, as the product's commands say it, instead of a traceback."""
    try:
        yield
    except PopcodeError as error:
        print(f"{command}: {first_line(error)}", file=sys.stderr)
        raise SystemExit(2) from None


def run_command(command: str, main: Callable[[], object]) -> NoReturn:
    """Exit with ``main``'s status (an int; anything else is 0), or as :func:`bad_input_exits` says."""
    with bad_input_exits(command):
        status = main()
    raise SystemExit(status if isinstance(status, int) else 0)
