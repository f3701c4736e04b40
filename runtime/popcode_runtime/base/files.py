"""Files in and out: JSON read with errors that name the file, and the one atomic write, so that a reader (a
resumed run, or another process writing beside this one) never sees half a file, and a file reported as written
survives a power cut.

Every file popcode, its trainer, benchmarks and experiments write goes through :func:`atomic_path` (or its
forms :func:`atomic_file`, :func:`write_bytes_atomic`, :func:`append_synced`): the data go to a temporary name
unique to the writer in the same folder, are synced to disk, renamed over the target, and the folder is synced so
the rename itself is on disk. A killed process only stops the page cache from being written back later; a power
cut drops whatever was not synced, so without the syncs a renamed file could read back empty.

A writer of many small files (a render's images) passes a :class:`SyncBatch` instead: each file is renamed into
place unsynced and the batch makes them all durable at once (a sync a file cost a render a third of its time:
bench/results/synced-writes-cost.md); such a writer marks its work done only after the batch's commit.
"""

from __future__ import annotations

import csv
import ctypes
import errno
import io
import json
import math
import os
import re
import secrets
import socket
import sys
import zlib
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from .checks import path as checked_path
from .errors import PopcodeError, library_step

# A JSON file larger than this is refused before it is parsed: Python holds about 25 bytes per byte of JSON,
# so this bounds a parse at about 1.6 GB (a BOP dataset's largest annotation or detections file is tens of MB).
MAX_JSON_BYTES = 1 << 26
MAX_JSON_INTEGER_DIGITS = 18  # ids, sizes and counts; longer integers are a corrupt or crafted file
MAX_NAME_BYTES = 200  # an output's name; ".<name>.<pid>-<host>.<random>.tmp" and "<name>.partial" stay within 255
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


def _host_tag() -> str:
    """8 hex digits of this machine's name: a process id means something only on the machine that gave it (runs on
    several machines may share a folder)."""
    return f"{zlib.crc32(socket.gethostname().encode()):08x}"


def temporary_name(path: Path) -> Path:
    """Where :func:`atomic_path` writes ``path`` first: ``.<name>.<pid>-<host>.<random>.tmp`` beside it, unique to
    the writer, so two writers of one file never share a temporary and a crashed one's leftover is never reused."""
    return path.with_name(f".{path.name}.{os.getpid()}-{_host_tag()}.{secrets.token_hex(4)}.tmp")


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs on this machine (POSIX only)."""
    try:
        os.kill(pid, 0)  # signal 0: only asks whether the process exists
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_temporaries(path: Path) -> list[Path]:
    """Remove the temporaries of ``path`` left by writers on this machine that are no longer running (a crash or a
    power cut mid-write); returns them.

    Called by the writers of large files (checkpoints, the crop cache) before they write; elsewhere a leftover is
    only ignored: its name is unique, hidden and never read, and listing a folder of thousands of rendered images
    on every write would cost more than the leftover. On Windows ``os.kill`` would end the process, so nothing is
    removed there.
    """
    folder = path.parent
    if os.name == "nt" or not folder.is_dir():
        return []
    pattern = re.compile(rf"\.{re.escape(path.name)}\.(\d+)-{_host_tag()}\.[0-9a-f]{{8}}\.tmp")
    removed = []
    for entry in os.scandir(folder):
        match = pattern.fullmatch(entry.name)
        if match and int(match.group(1)) != os.getpid() and not _alive(int(match.group(1))):
            Path(entry.path).unlink(missing_ok=True)
            removed.append(Path(entry.path))
    return removed


def sync_file(path: Path) -> None:
    """Force ``path``'s data to disk (through a descriptor of its own: the writer may have closed its handle)."""
    descriptor = os.open(path, os.O_RDWR | getattr(os, "O_BINARY", 0))
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def sync_folder(folder: Path) -> None:
    """Force ``folder``'s entries (a rename into it) to disk. Windows cannot open a folder, and a few file systems
    refuse to sync one; there the rename is as durable as the system makes it."""
    if os.name == "nt":
        return
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    except OSError as error:
        if error.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(descriptor)


_LIBC = ctypes.CDLL(None, use_errno=True) if sys.platform.startswith("linux") else None


def sync_file_system(folder: Path) -> bool:
    """Force everything written to ``folder``'s file system to disk with one ``syncfs`` (Linux); False where the
    system has none or refuses it (the caller then syncs file by file)."""
    syncfs = getattr(_LIBC, "syncfs", None)
    if syncfs is None:
        return False
    descriptor = os.open(folder, os.O_RDONLY)
    try:
        return syncfs(descriptor) == 0
    finally:
        os.close(descriptor)


class SyncBatch:
    """Atomic writes whose syncs are paid once for many files: :func:`atomic_path` given a batch renames each file
    into place unsynced and :meth:`commit` makes every file written so far durable (one ``syncfs`` per file system,
    else an ``fsync`` of each file and folder). Until the commit a power cut may leave any of them empty, so a
    writer marks its work done only after it."""

    def __init__(self) -> None:
        self._written: list[Path] = []

    def add(self, path: Path) -> None:
        self._written.append(path)

    def commit(self) -> None:
        written, self._written = self._written, []
        by_device: dict[int, list[Path]] = {}
        for path in written:
            by_device.setdefault(path.parent.stat().st_dev, []).append(path)
        for paths in by_device.values():
            if not sync_file_system(paths[0].parent):
                for path in paths:
                    sync_file(path)
                for folder in dict.fromkeys(path.parent for path in paths):
                    sync_folder(folder)


@contextmanager
def atomic_path(path: str | os.PathLike, batch: SyncBatch | None = None) -> Iterator[Path]:
    """The one atomic write: yields a temporary path beside ``path`` for a writer that wants a file name
    (``torch.save``, ``np.lib.format.open_memmap``); when the block ends without an error the file is synced,
    renamed over ``path`` and the folder synced (with a ``batch``: renamed, and synced by the batch's commit); on
    an error it is removed and ``path`` keeps what it held."""
    path = Path(path)
    temporary = temporary_name(path)
    try:
        yield temporary
        if batch is None:
            sync_file(temporary)
        os.replace(temporary, path)
    finally:
        temporary.unlink(missing_ok=True)
    if batch is None:
        sync_folder(path.parent)
    else:
        batch.add(path)


@contextmanager
def atomic_file(path: str | os.PathLike, mode: str = "wb", batch: SyncBatch | None = None,
                **open_arguments: Any) -> Iterator[IO]:
    """:func:`atomic_path` for a writer that wants an open handle (``np.save``, ``csv.writer``)."""
    with atomic_path(path, batch) as temporary, temporary.open(mode, **open_arguments) as handle:
        yield handle


def write_bytes_atomic(path: Path, data: bytes, batch: SyncBatch | None = None) -> None:
    """``data`` as the whole of ``path``, written with :func:`atomic_path`."""
    with atomic_file(path, batch=batch) as handle:
        handle.write(data)


def copy_file_atomic(source: Path, target: Path) -> None:
    """A copy of ``source`` at ``target``, written with :func:`atomic_path` (``shutil.copy`` syncs nothing)."""
    write_bytes_atomic(target, Path(source).read_bytes())


def flush_to_disk(handle: IO) -> None:
    """What was written to an open ``handle`` so far, on disk: after this, a power cut loses none of it."""
    handle.flush()
    os.fsync(handle.fileno())


def append_synced(path: Path, text: str, first: str = "") -> None:
    """Append ``text`` to ``path`` and sync it; a missing or empty file is written whole (``first``, a header,
    then ``text``) with :func:`write_bytes_atomic`, so its creation is synced with its folder too."""
    if not path.exists() or path.stat().st_size == 0:
        write_bytes_atomic(path, (first + text).encode())
        return
    with path.open("a", encoding="utf-8", newline="") as handle:
        handle.write(text)
        flush_to_disk(handle)


def csv_text(rows: Iterable[Sequence[Any]]) -> str:
    """``rows`` as CSV text, as ``csv.writer`` writes them to a file (what :func:`append_synced` appends)."""
    text = io.StringIO(newline="")
    csv.writer(text).writerows(rows)
    return text.getvalue()


def json_bytes(data: Any) -> bytes:
    """How popcode writes a JSON file (its bytes, so a writer can compare them with a file's)."""
    return json.dumps(data, indent=1).encode()


def write_json_atomic(path: Path, data: Any, batch: SyncBatch | None = None) -> None:
    write_bytes_atomic(path, json_bytes(data), batch)


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


def write_picture_atomic(path: str | os.PathLike, image_bgr: np.ndarray, params: Sequence[int] = (),
                         batch: SyncBatch | None = None) -> Path:
    """Encode a BGR (or grey) uint8/uint16 image in the format its suffix names (OpenCV's ``params``, such as
    ``[cv2.IMWRITE_JPEG_QUALITY, 85]``) and write it atomically."""
    path = check_picture_path(path)
    with library_step(f"encode {path.name} as {path.suffix.lstrip('.').upper()}"):
        ok, encoded = cv2.imencode(path.suffix.lower(), np.ascontiguousarray(image_bgr), list(params))
    if not ok:
        raise PopcodeError(f"cannot encode {path.name} as {path.suffix.lstrip('.').upper()}")
    write_bytes_atomic(path, encoded.tobytes(), batch)
    return path


def write_png_atomic(path: Path, image: np.ndarray, batch: SyncBatch | None = None) -> None:
    """PNG of a grey ``(H, W)`` or RGB ``(H, W, 3)`` uint8/uint16 image."""
    write_picture_atomic(path, image[..., ::-1] if image.ndim == 3 else image, batch=batch)  # OpenCV writes BGR
