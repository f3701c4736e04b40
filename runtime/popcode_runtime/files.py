"""Atomic file writes: a reader (or another process writing beside this one) never sees half a file.

The trainer writes its images, JSON and models through :func:`write_bytes_atomic` too.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from .checks import path as checked_path
from .errors import PopcodeError, library_step

PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary name in the same folder, then rename over ``path``; no temporary file is left behind."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_bytes(data)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def check_writable_file(value: str | os.PathLike, what: str) -> Path:
    """``value`` as a path that can be written atomically: its folder exists and is writable, it is not a folder.

    Checked before long work starts, so a typo costs a line, not the run.
    """
    path = checked_path(value, what)
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise PopcodeError(f"{what} {path} is a folder, not a file")
    if not folder.is_dir():
        raise PopcodeError(f"{what} {path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PopcodeError(f"{what} {path}: folder {folder} is not writable")
    return path


def check_picture_path(value: str | os.PathLike, what: str = "picture path") -> Path:
    """``value`` as a writable image file whose suffix names a format OpenCV writes (PNG, JPEG, ...)."""
    path = check_writable_file(value, what)
    if path.suffix.lower() not in PICTURE_SUFFIXES or not cv2.haveImageWriter(str(path)):
        raise PopcodeError(f"{what} {path}: unknown image format {path.suffix!r}; use one of "
                           f"{', '.join(PICTURE_SUFFIXES)}")
    return path


def write_picture_atomic(path: str | os.PathLike, image_bgr: np.ndarray) -> Path:
    """Encode a BGR (or grey) uint8/uint16 image in the format its suffix names and write it atomically."""
    path = check_picture_path(path)
    with library_step(f"encode {path.name} as {path.suffix.lstrip('.').upper()}"):
        ok, encoded = cv2.imencode(path.suffix.lower(), np.ascontiguousarray(image_bgr))
    if not ok:
        raise PopcodeError(f"cannot encode {path.name} as {path.suffix.lstrip('.').upper()}")
    write_bytes_atomic(path, encoded.tobytes())
    return path
