"""Typed, range-checked values at the runtime's boundary (model metadata, Python API arguments).

Metadata is JSON written by a trainer, a script or a hand; API arguments come
from any caller. Each reader here accepts exactly one kind of value and names
the field when it refuses, so a bad value becomes one :class:`PopcodeError`
line instead of a ``TypeError`` three calls later or a silent coercion
(``642.0`` read as 642, ``"2"`` as 2).
"""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .errors import PopcodeError


def shown(value: Any, width: int = 60) -> str:
    """``value`` as a message shows it: its repr (an array's list), cut to ``width`` characters."""
    try:
        text = repr(value.tolist() if isinstance(value, np.ndarray) else value)
    except ValueError:  # an int of more digits than Python converts to text, or a container holding one
        if isinstance(value, int):
            return f"an integer of about {int(value.bit_length() * 0.30103)} digits"
        return f"a {type(value).__name__} holding an integer too long to show"
    return text if len(text) <= width else text[: width - 3] + "..."


def integer(value: Any, name: str, low: int | None = None, high: int | None = None) -> int:
    """``value`` as an ``int`` within ``[low, high]``; a bool, float or string is refused, not coerced."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise PopcodeError(f"{name} must be an integer, got {shown(value)} ({type(value).__name__})")
    result = int(value)
    if (low is not None and result < low) or (high is not None and result > high):
        raise PopcodeError(f"{name} must lie in {_range_text(low, high)}, got {result}")
    return result


def number(value: Any, name: str, low: float | None = None, high: float | None = None) -> float:
    """``value`` as a finite ``float`` within ``[low, high]``; bools and strings are refused."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise PopcodeError(f"{name} must be a number, got {shown(value)} ({type(value).__name__})")
    try:
        result = float(value)
    except OverflowError:  # an integer beyond a float's range (JSON allows any number of digits)
        result = math.inf
    if not math.isfinite(result):
        raise PopcodeError(f"{name} must be finite, got {shown(value)}")
    if (low is not None and result < low) or (high is not None and result > high):
        raise PopcodeError(f"{name} must lie in {_range_text(low, high)}, got {result:g}")
    return result


def flag(value: Any, name: str) -> bool:
    """``value`` as a ``bool``; ``0``, ``"false"`` and ``None`` are refused (they read as the opposite too easily)."""
    if not isinstance(value, (bool, np.bool_)):
        raise PopcodeError(f"{name} must be true or false, got {shown(value)} ({type(value).__name__})")
    return bool(value)


def mapping(value: Any, name: str) -> Mapping[str, Any]:
    """``value`` itself if it is a mapping (a JSON object)."""
    if not isinstance(value, Mapping):
        raise PopcodeError(f"{name} must be an object (a mapping), got {shown(value)} ({type(value).__name__})")
    return value


def path(value: Any, name: str) -> Path:
    """``value`` as a ``Path``: a string or path-like, nothing else (``Path(None)`` is a ``TypeError``)."""
    if not isinstance(value, (str, os.PathLike)):
        raise PopcodeError(f"{name} must be a file path, got {shown(value)} ({type(value).__name__})")
    return Path(value)


def number_array(value: Any, name: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape`` (``None``: any length along that axis)."""
    if isinstance(value, (str, bytes)):
        raise PopcodeError(f"{name} must be numbers, got the text {shown(value)}")
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as error:
        raise PopcodeError(f"{name} must be numbers of shape {_shape_text(shape)}, got {shown(value)}") from error
    if array.ndim != len(shape) or any(want is not None and got != want for got, want in zip(array.shape, shape,
                                                                                             strict=True)):
        raise PopcodeError(f"{name} must have shape {_shape_text(shape)}, got {array.shape}")
    if not np.isfinite(array).all():
        raise PopcodeError(f"{name} contains NaN or inf")
    return array


def _range_text(low: float | None, high: float | None) -> str:
    return f"[{'-inf' if low is None else f'{low:g}'}, {'inf' if high is None else f'{high:g}'}]"


def _shape_text(shape: tuple[int | None, ...]) -> str:
    return "(" + ", ".join("N" if n is None else str(n) for n in shape) + ")"
