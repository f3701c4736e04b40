"""The parser of both command lines (``popcode``, ``popcode-train``): a usage error is one line, as every refusal.

argparse answers a bad option (a clash of mutually exclusive options, a value
its type refuses, an option the command lacks) with its usage block and a
line; here it is the line alone, naming the command and where its options are
listed, and exit code 2. An option the command lacks is named with the
command's own name: argparse reports it from the top-level parser, which does
not know which command was meant.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import Any, NoReturn


class CommandParser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose errors are one line; its subcommands' parsers are of this class too."""

    _commands: argparse._SubParsersAction | None = None

    def add_subparsers(self, **kwargs: Any) -> argparse._SubParsersAction:
        self._commands = super().add_subparsers(**kwargs)
        return self._commands

    def parse_args(self, args: Sequence[str] | None = None,  # type: ignore[override]
                   namespace: argparse.Namespace | None = None) -> argparse.Namespace:
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:
            self._command_parser(parsed).error(f"unrecognized arguments: {' '.join(extras)}")
        return parsed

    def _command_parser(self, parsed: argparse.Namespace) -> CommandParser:
        """The parser of the command ``parsed`` names (this one where there is none)."""
        if self._commands is None:
            return self
        found = self._commands.choices.get(getattr(parsed, self._commands.dest, None))
        return found if isinstance(found, CommandParser) else self

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")
