"""The exit of ``python -m bench.<name>`` (no torch here: some benchmarks need the runtime only)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import NoReturn

from popcode_runtime.errors import PopcodeError, first_line


def run_command(name: str, main: Callable[[], object]) -> NoReturn:
    """Exit with ``main``'s status (an int; anything else is 0), or, for bad input (a ``PopcodeError``), with one
    line and status 2 as the product's commands say it, instead of a traceback."""
    try:
        status = main()
    except PopcodeError as error:
        print(f"bench.{name}: {first_line(error)}", file=sys.stderr)
        raise SystemExit(2) from None
    raise SystemExit(status if isinstance(status, int) else 0)
