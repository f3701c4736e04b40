"""Enums whose members are their text: equal to it, printed as it, written to JSON as it."""

from __future__ import annotations

import enum


class TextEnum(str, enum.Enum):
    """A ``(str, Enum)`` that formats as its value on every Python (3.11 changed f-strings of mixed-in enums)."""

    __str__ = str.__str__
    __format__ = str.__format__

    @classmethod
    def values(cls) -> tuple[str, ...]:
        """Every member's text, in definition order (for messages and choices)."""
        return tuple(member.value for member in cls)
