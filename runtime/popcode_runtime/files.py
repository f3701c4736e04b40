"""Files in and out: JSON read with errors that name the file, and atomic writes, so that a reader (a resumed
run, or a render shard running beside this one) never sees half a file."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .errors import PopcodeError

MAX_JSON_BYTES = 1 << 28  # a BOP annotation or detections file larger than this is refused before it is parsed


def require_folder(path: Path, what: str) -> Path:
    """``path`` if it is a folder; a file where a folder belongs (a ``.pt`` for a split) is named as such."""
    if path.is_file():
        raise PopcodeError(f"{what} {path} is a file, not a folder")
    if not path.is_dir():
        raise PopcodeError(f"{what} not found: {path}")
    return path


def read_json(path: Path) -> Any:
    """Parsed JSON, or a PopcodeError that names the file (missing, too large, not JSON)."""
    if not path.is_file():
        raise PopcodeError(f"missing file {path}")
    if path.stat().st_size > MAX_JSON_BYTES:
        raise PopcodeError(f"{path} is {path.stat().st_size >> 20} MiB; JSON files over {MAX_JSON_BYTES >> 20} MiB "
                           "are refused")
    try:
        with path.open() as file:
            return json.load(file)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise PopcodeError(f"{path} is not valid JSON: {error}") from error


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
