"""``popcode run``'s resumable results file: ``<out>.partial`` while a run writes, the BOP19 CSV when it ends.

Each finished image's estimate lines are appended to the partial file with a
closing mark that carries a checksum of the lines and of the run's fingerprint
(what the results depend on: :mod:`.run_fingerprint`). A run that is stopped
resumes from the last closed image; a torn tail is dropped, an edited or
foreign file refused. The results file appears (atomically) only when every
image is done, and ``<out>.lock`` keeps a second run off the same ``out``.

With depth the BOP19 format has no place to say where a translation came from,
so ``<out stem>.translation.csv`` does, one line per estimate in the same order:
``scene_id,im_id,obj_id,source,depth_fit,note`` (source ``box``, ``depth`` or
``refined``; the note says why an instance kept the box's translation). In the
partial file these lines follow the image's estimates, marked, under the
image's checksum.
"""

from __future__ import annotations

import hashlib
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path
from typing import IO

from ..base.errors import PopcodeError
from ..base.files import flush_to_disk, name_id, refuse_existing, write_bytes_atomic
from ..base.output_lock import OutputLock
from ..bop.bop19_csv import PoseEstimate, format_estimate, parse_estimate, write_bop19_lines
from ..geometry.rotations import is_rotation

PARTIAL_SUFFIX = ".partial"
LOCK_SUFFIX = ".lock"
CHECKSUM_CHARS = 16  # hex digits of SHA-256 closing each image in a partial file
MAX_PARTIAL_LINE_BYTES = 1024  # a partial file's line is about 400; bounds what a resume reads
RUN_MARK = "#popcode-run "  # first line of a partial file: what the run was made from
DONE_MARK = "#done "  # closes one image's estimates
SOURCE_MARK = "#translation "  # a line of the translation file, kept in the partial file with its image's estimates
SOURCE_HEADER = "scene_id,im_id,obj_id,source,depth_fit,note"

ImageKey = tuple[int, int]  # (scene_id, im_id)


def _done_key(line: str) -> tuple[ImageKey, str] | None:
    """The image a whole ``#done scene_id im_id checksum`` line closes, and its checksum; None for any other line
    (a torn mark too)."""
    fields = line[len(DONE_MARK):].split(" ") if line.startswith(DONE_MARK) else []
    ids = [name_id(field) for field in fields[:2]]
    if len(fields) != 3 or None in ids or len(fields[2]) != CHECKSUM_CHARS:
        return None
    return (ids[0], ids[1]), fields[2]


def _checksum(lines: Sequence[str], fingerprint: str) -> str:
    """What closes an image's lines: a torn, edited or foreign line no longer matches it, nor an image's lines from
    the partial file of another run (its fingerprint differs)."""
    return hashlib.sha256("\n".join([fingerprint, *lines]).encode()).hexdigest()[:CHECKSUM_CHARS]


class PartialResults:
    """``<out>.partial``: the estimate lines of finished images, each image closed by a ``#done`` line that carries
    a checksum of its lines and the run's fingerprint; ``<out>.lock`` held while a run writes them.

    Made before the run knows its detections (a detector's run detects after it): it takes the lock and refuses a
    second run writing the same ``out``, a finished ``out`` (replaced only with ``overwrite``) and a partial file
    made from other models, detections, split or options. :meth:`resume` then keeps every closed image (a torn
    tail from a killed run is dropped) and refuses a file whose closed images were edited. Closed (lock released)
    when a ``with`` block ends, however it ends.
    """

    def __init__(self, out: Path, fingerprint: str, overwrite: bool = False) -> None:
        self.out, self.fingerprint = out, fingerprint
        self.path, _, self.sources = companion_paths(out)
        self.blocks: dict[ImageKey, list[str]] = {}  # each closed image's lines, its closing mark last
        self._handle: IO[str] | None = None
        self._lock = out_lock(out)
        try:
            if not self.path.exists():  # a finished run's files; with a partial beside them, a rerun that resumes
                refuse_existing(out, "--out", overwrite)
                refuse_existing(self.sources, "--out's translation sources", overwrite)
            elif not self.path.is_file():  # a FIFO would block the read forever, /dev/zero never end it
                raise self._refuse("is not a regular file")
            else:
                with self.path.open("rb") as handle:  # another run's partial is refused as such, whatever its size
                    if handle.readline(MAX_PARTIAL_LINE_BYTES).rstrip(b"\n") != (RUN_MARK + fingerprint).encode():
                        raise self._refuse("holds the partial results of a run with other models, detections, "
                                           "split or options")
        except BaseException:
            self._lock.release()
            raise

    def __enter__(self) -> PartialResults:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def done(self) -> Collection[ImageKey]:
        """The images closed so far."""
        return self.blocks.keys()

    def _refuse(self, why: str) -> PopcodeError:
        return PopcodeError(f"{self.path} {why}; remove it to start again, or rerun the command that made it")

    def resume(self, expected: Mapping[ImageKey, Sequence[int]]) -> None:
        """Keep the closed images of an earlier run's partial file, checked against ``expected`` (image -> the
        object ids of its detections, in order: what this run would write for it), and open the file anew."""
        if self.path.exists():
            self._read(expected)
        lines = [line for block in self.blocks.values() for line in block]
        write_bytes_atomic(self.path, "\n".join([RUN_MARK + self.fingerprint, *lines]).encode() + b"\n")
        self._handle = self.path.open("a")

    def _read(self, expected: Mapping[ImageKey, Sequence[int]]) -> None:
        # at most an estimate and a translation line per detection and a closing mark per image
        limit = MAX_PARTIAL_LINE_BYTES * (2 * sum(len(ids) for ids in expected.values()) + len(expected))
        with self.path.open("rb") as handle:
            handle.readline(MAX_PARTIAL_LINE_BYTES)  # the header, checked when the file was claimed
            data = handle.read(limit + 1)
        if len(data) > limit:
            raise self._refuse(f"is larger than this run's results can be ({limit} bytes after its first line)")
        try:
            text = data.decode("utf-8").split("\n")
        except UnicodeDecodeError as error:
            raise self._refuse(f"is not text ({error.reason} at byte {error.start})") from error
        blocks: list[tuple[list[str], tuple[ImageKey, str] | None]] = []
        pending: list[str] = []
        for line in text:
            if line.startswith(DONE_MARK):
                blocks.append((pending, _done_key(line)))
                pending = []
            elif line:
                pending.append(line)  # lines after the last mark: an image a killed run did not close
        # A killed run can tear only its last image (lines, mark or both); anything wrong before that was changed.
        while blocks and _block_problem(*blocks[-1], expected, self.done, self.fingerprint) is not None:
            blocks.pop()
        for lines, mark in blocks:
            problem = _block_problem(lines, mark, expected, self.done, self.fingerprint)
            if problem is not None or mark is None:
                raise self._refuse(f"was changed after it was written ({problem})")
            key, checksum = mark
            self.blocks[key] = [*lines, f"{DONE_MARK}{key[0]} {key[1]} {checksum}"]

    def add(self, key: ImageKey, estimates: Sequence[PoseEstimate], sources: Sequence[str] = ()) -> None:
        """Append one image's estimates, its lines of the translation file (``sources``) and its closing mark,
        flushed to disk."""
        lines = [format_estimate(est) for est in estimates] + [SOURCE_MARK + line for line in sources]
        lines.append(f"{DONE_MARK}{key[0]} {key[1]} {_checksum(lines, self.fingerprint)}")
        self._handle.write("\n".join(lines) + "\n")
        flush_to_disk(self._handle)
        self.blocks[key] = lines

    def finish(self) -> None:
        """Write the results file (header and every estimate, images in the run's order whatever the order of
        the partial file's blocks) atomically and remove the partial file."""
        self._handle.close()
        lines = [line for key in sorted(self.blocks) for line in self.blocks[key]]
        write_bop19_lines(self.out, [line for line in lines if not line.startswith("#")])
        sources = [line[len(SOURCE_MARK):] for line in lines if line.startswith(SOURCE_MARK)]
        if sources:
            write_bytes_atomic(self.sources, "\n".join([SOURCE_HEADER, *sources]).encode() + b"\n")
        else:  # one from a results file this run replaced would describe other estimates
            self.sources.unlink(missing_ok=True)
        self.path.unlink()

    def close(self) -> None:
        if self._handle is not None:
            self._handle.close()
            self._handle = None
        self._lock.release()


def _block_problem(lines: Sequence[str], mark: tuple[ImageKey, str] | None,
                   expected: Mapping[ImageKey, Sequence[int]], done: Collection[ImageKey],
                   fingerprint: str) -> str | None:
    """What is wrong with one image's lines in a partial file of the run ``fingerprint``, or None."""
    if mark is None:
        return "a closing mark is torn or malformed"
    key, checksum = mark
    if key not in expected:
        return f"scene {key[0]} image {key[1]} is not among this run's images"
    if key in done:
        return f"scene {key[0]} image {key[1]} is closed twice"
    if _checksum(lines, fingerprint) != checksum:
        return f"the lines of scene {key[0]} image {key[1]} do not match their checksum"
    try:
        estimates = [parse_estimate(line, f"scene {key[0]} image {key[1]}") for line in lines
                     if not line.startswith(SOURCE_MARK)]
    except PopcodeError as error:
        return str(error)
    if [(e.scene_id, e.im_id) for e in estimates] != [key] * len(estimates) or \
            [e.obj_id for e in estimates] != list(expected[key]):
        return f"the lines of scene {key[0]} image {key[1]} are not its detections' estimates"
    for e in estimates:  # what popcode writes: a score that is a confidence, a measured time, a rotation
        if not 0.0 <= e.score <= 1.0 or e.time_s < 0.0 or not is_rotation(e.R_m2c):
            return (f"the line of scene {key[0]} image {key[1]} object {e.obj_id} holds values popcode never writes "
                    f"(score {e.score!r}, time {e.time_s!r}, R {'a' if is_rotation(e.R_m2c) else 'no'} rotation)")
    return None


def sources_path(out: Path) -> Path:
    """Where a run with depth says each estimate's translation source: ``<out stem>.translation<out suffix>``
    (``results.translation.csv``; ``results.translation`` for ``results``), one per results file."""
    return out.with_name(f"{out.stem}.translation{out.suffix}")


def out_lock(out: Path) -> OutputLock:
    """``<out>.lock``, which keeps a second ``popcode run`` or ``popcode detect`` off the same ``out``."""
    lock = companion_paths(out)[1]
    return OutputLock(lock, f"another popcode detect or run is writing {out} (it holds {lock.name}); wait for it or "
                      "choose another --out")


def companion_paths(out: Path) -> tuple[Path, Path, Path]:
    """The files a run writes beside ``out``: its partial results, its lock and its translation sources."""
    return out.with_name(out.name + PARTIAL_SUFFIX), out.with_name(out.name + LOCK_SUFFIX), sources_path(out)
