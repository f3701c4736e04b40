"""Files in and out: JSON read with errors that name the file, and atomic writes, so that a reader (a resumed
run, or another process writing beside this one) never sees half a file.

The trainer writes its images, JSON and models through these functions too.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .checks import path as checked_path
from .errors import PopcodeError, library_step

# A JSON file larger than this is refused before it is parsed: Python holds about 25 bytes per byte of JSON,
# so this bounds a parse at about 1.6 GB (a BOP dataset's largest annotation or detections file is tens of MB).
MAX_JSON_BYTES = 1 << 26
MAX_JSON_INTEGER_DIGITS = 18  # ids, sizes and counts; longer integers are a corrupt or crafted file
MAX_NAME_BYTES = 200  # an output's name; ".<name>.<pid>.tmp" and "<name>.partial" must stay within 255
PICTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")


def name_id(name: str) -> int | None:
    """The id a BOP file or folder name (``000003``, ``3``) or JSON key stands for; None for any other name.

    ASCII digits only: Python's ``int`` also takes ``" 3"``, ``"+3"``, ``"3_0"`` and other scripts' digits; at
    most as many as JSON integers (:data:`MAX_JSON_INTEGER_DIGITS`).
    """
    digits = name.isascii() and name.isdigit() and len(name) <= MAX_JSON_INTEGER_DIGITS
    return int(name) if digits else None


def require_folder(path: Path, what: str) -> Path:
    """``path`` if it is a folder; a file where a folder belongs (a ``.pt`` for a split) is named as such."""
    if path.is_file():
        raise PopcodeError(f"{what} {path} is a file, not a folder")
    if not path.is_dir():
        raise PopcodeError(f"{what} not found: {path}")
    return path


def read_json(path: Path) -> Any:
    """Parsed JSON, or a PopcodeError that names the file (missing, too large, not JSON, nested too deep, numbers
    outside what JSON of this project holds: NaN/Infinity, floats that overflow, integers of many digits).

    The one reader of BOP annotations, detections and run files, so every reader has the same bounds.
    """
    if not path.is_file():
        raise PopcodeError(f"missing file {path}")
    if path.stat().st_size > MAX_JSON_BYTES:
        raise PopcodeError(f"{path} is {path.stat().st_size >> 20} MiB; JSON files over {MAX_JSON_BYTES >> 20} MiB "
                           "are refused")
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as error:
        raise PopcodeError(f"{path} is not valid JSON: {error}") from error
    return parse_json(text, str(path))


def parse_json(text: str, name: str) -> Any:
    """JSON text parsed with :func:`read_json`'s bounds on numbers and nesting; errors name ``name``."""
    try:
        return json.loads(text, parse_int=_bounded_int, parse_float=_finite_float, parse_constant=_no_constant)
    except (json.JSONDecodeError, _BadNumberError) as error:
        first = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise PopcodeError(f"{name} is not valid JSON: {first}") from error
    except RecursionError as error:  # the parser recurses once per level of nesting
        raise PopcodeError(f"{name} nests JSON too deeply; refused") from error


class _BadNumberError(ValueError):
    """A number JSON allows but this project's files never hold."""


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_JSON_INTEGER_DIGITS:
        raise _BadNumberError(f"an integer of {len(text.lstrip('-'))} digits (at most {MAX_JSON_INTEGER_DIGITS})")
    return int(text)


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _BadNumberError(f"the number {text[:20]}{'...' if len(text) > 20 else ''} overflows a float")
    return value


def _no_constant(name: str) -> float:
    raise _BadNumberError(f"{name} is not a JSON number")


def write_bytes_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary name in the same folder, then rename over ``path``; no temporary file is left behind."""
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        temporary.write_bytes(data)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)


def json_bytes(data: Any) -> bytes:
    """How popcode writes a JSON file (its bytes, so a writer can compare them with a file's)."""
    return json.dumps(data, indent=1).encode()


def write_json_atomic(path: Path, data: Any) -> None:
    write_bytes_atomic(path, json_bytes(data))


def check_writable_file(value: str | os.PathLike, what: str, inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """``value`` as a path that can be written atomically: its folder exists and is writable, it is not a folder
    (nor named as one, ``results/``), it is none of the command's ``inputs`` (files and folders) and lies in none.

    Checked before long work starts, so a typo costs a line, not the run.
    """
    path = checked_path(value, what)
    if os.fspath(value).endswith(tuple(sep for sep in (os.sep, os.altsep) if sep)):
        raise PopcodeError(f"{what} {os.fspath(value)} ends with a path separator, so it names a folder; give a file "
                           f"name (such as {os.fspath(value)}results.csv)")
    refuse_inputs(path, what, inputs)
    folder = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise PopcodeError(f"{what} {path} is a folder, not a file")
    if path.is_symlink() or (path.exists() and not path.is_file()):  # a rename would replace a device or FIFO
        raise PopcodeError(f"{what} {path} is not a regular file (a link, device or FIFO); outputs are written "
                           "only as regular files: choose another path")
    if not folder.is_dir():
        raise PopcodeError(f"{what} {path}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PopcodeError(f"{what} {path}: folder {folder} is not writable")
    if len(path.name.encode()) > MAX_NAME_BYTES:
        raise PopcodeError(f"{what} {path}: the name is {len(path.name.encode())} bytes; at most {MAX_NAME_BYTES} "
                           "(its temporary and partial files add to it, and file systems stop at 255)")
    return path


OVERWRITE_HELP = "replace output files that exist already (never a file the command reads)"


def refuse_existing(path: Path, what: str, overwrite: bool) -> Path:
    """``path``, unless it exists and ``overwrite`` is off: the one rule for outputs that exist, in every command
    (an output is never an input, :func:`check_writable_file`; folders of long work resume instead)."""
    if not overwrite and (path.exists() or path.is_symlink()):
        raise PopcodeError(f"{what} {path} exists already; pass --overwrite to replace it, or choose another path")
    return path


def check_output_file(value: str | os.PathLike, what: str, inputs: Iterable[str | os.PathLike] = (),
                      overwrite: bool = False) -> Path:
    """``value`` as a new output file (:func:`check_writable_file`), refused if it exists unless ``overwrite``."""
    return refuse_existing(check_writable_file(value, what, inputs), what, overwrite)


def refuse_inputs(path: Path, what: str, inputs: Iterable[str | os.PathLike]) -> Path:
    """``path`` (an output file or folder), unless it is one of the command's ``inputs`` or lies in one."""
    target = Path(os.path.realpath(path))  # realpath, not Path.resolve: a symbolic link loop is no error here
    for source in (Path(os.path.realpath(source)) for source in inputs):
        if target == source or (source.is_dir() and target.is_relative_to(source)):
            raise PopcodeError(f"{what} {path} {'is' if target == source else 'lies in'} the input {source}; "
                               "an output never replaces or joins what the command reads: choose another path")
    return path


def check_picture_path(value: str | os.PathLike, what: str = "picture path", inputs: Iterable[str | os.PathLike] = (),
                       overwrite: bool = True) -> Path:
    """``value`` as a writable image file whose suffix names a format OpenCV writes (PNG, JPEG, ...); with
    ``overwrite`` off an existing file is refused (:func:`refuse_existing`)."""
    path = check_output_file(value, what, inputs, overwrite)
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


def write_png_atomic(path: Path, image: np.ndarray) -> None:
    """PNG of a grey ``(H, W)`` or RGB ``(H, W, 3)`` uint8/uint16 image."""
    write_picture_atomic(path, image[..., ::-1] if image.ndim == 3 else image)  # OpenCV writes BGR
