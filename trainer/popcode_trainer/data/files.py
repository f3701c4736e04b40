"""Atomic file writes (the runtime's ``write_bytes_atomic``): a reader (or a render shard running beside this one)
never sees half a file."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.errors import PopcodeError
from popcode_runtime.files import write_bytes_atomic, write_picture_atomic


def require_folder(path: Path, what: str) -> Path:
    """``path`` if it is a folder; a file where a folder belongs (a ``.pt`` for a split) is named as such."""
    if path.is_file():
        raise PopcodeError(f"{what} {path} is a file, not a folder")
    if not path.is_dir():
        raise PopcodeError(f"{what} not found: {path}")
    return path


def write_json_atomic(path: Path, data: Any) -> None:
    write_bytes_atomic(path, json.dumps(data, indent=1).encode())


def write_png_atomic(path: Path, image: np.ndarray) -> None:
    """PNG of a grey ``(H, W)`` or RGB ``(H, W, 3)`` uint8/uint16 image."""
    write_picture_atomic(path, image[..., ::-1] if image.ndim == 3 else image)  # OpenCV writes BGR
