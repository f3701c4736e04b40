"""Atomic file writes: a reader (or a render shard running beside this one) never sees half a file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from popcode_runtime.errors import PopcodeError


def require_folder(path: Path, what: str) -> Path:
    """``path`` if it is a folder; a file where a folder belongs (a ``.pt`` for a split) is named as such."""
    if path.is_file():
        raise PopcodeError(f"{what} {path} is a file, not a folder")
    if not path.is_dir():
        raise PopcodeError(f"{what} not found: {path}")
    return path


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary name in the same folder, then rename over ``path``."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    temporary.write_bytes(data)
    os.replace(temporary, path)


def write_json_atomic(path: Path, data: Any) -> None:
    write_bytes_atomic(path, json.dumps(data, indent=1).encode())


def write_png_atomic(path: Path, image: np.ndarray) -> None:
    """PNG of a grey ``(H, W)`` or RGB ``(H, W, 3)`` uint8/uint16 image."""
    if image.ndim == 3:
        image = image[..., ::-1]  # OpenCV writes BGR
    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:
        raise PopcodeError(f"cannot encode {path.name} as PNG")
    write_bytes_atomic(path, encoded.tobytes())
