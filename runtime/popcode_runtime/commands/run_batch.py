"""``popcode run``: a pose for every detection of a BOP split, written as a BOP19 results file.

popcode is the pose stage after any 2-D detector: each image is read once, the
boxes of each model go through it in one batch (:mod:`popcode_runtime.inference.image_loop`), the
translation is fitted to each box with the image's ``cam_K``, and the
image's estimates are appended to ``<out>.partial`` with a closing mark. A run
that is stopped resumes from the last closed image; the results file appears
(atomically) only when every image is done. The ``time`` of an image is the
measured seconds of popcode's work on it (read, crop, network, decode,
translation) plus the detector's own time when the detections give one; the
``score`` is the detection score times the calibrated confidence where the
model has a calibrator.

With depth (``popcode run --depth``) each image's depth image gives the
translation (:mod:`popcode_runtime.depth.surface_fit`), refined with ``--refine``. The BOP19 format has no
place to say where a translation came from, so ``<out stem>.translation.csv``
does, one line per estimate in the same order: ``scene_id,im_id,obj_id,source,
depth_fit,note`` (source ``box``, ``depth`` or ``refined``; the note says why an
instance kept the box's translation). In the partial file these lines follow
the image's estimates, marked, under the image's checksum.
"""

from __future__ import annotations

import csv
import hashlib
import io
import os
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from itertools import islice
from pathlib import Path

import numpy as np

from ..base.errors import PopcodeError
from ..base.files import check_output_file, name_id, refuse_existing, write_bytes_atomic, write_picture_atomic
from ..base.image_size import image_size
from ..bop.bop19_csv import PoseEstimate, format_estimate, parse_estimate, write_bop19_lines
from ..bop.detections import Detection
from ..bop.split import SplitImage
from ..depth.icp import require_small_gicp
from ..geometry.crop import check_box
from ..geometry.rotations import is_rotation
from ..inference.estimator import PoseEstimator, Prediction
from ..inference.image_loop import ImageBoxes, estimate_images, route_objects
from .drawing import draw_predictions

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None  # type: ignore[assignment]

PARTIAL_SUFFIX = ".partial"
LOCK_SUFFIX = ".lock"
CHECKSUM_CHARS = 16  # hex digits of SHA-256 closing each image in a partial file
MAX_PARTIAL_LINE_BYTES = 1024  # a partial file's line is about 400; bounds what a resume reads
MAX_WEIGHT_FILES = 1000  # files beside a model looked at for its external weights
RUN_MARK = "#popcode-run "  # first line of a partial file: what the run was made from
DONE_MARK = "#done "  # closes one image's estimates
SOURCE_MARK = "#translation "  # a line of the translation file, kept in the partial file with its image's estimates
SOURCE_HEADER = "scene_id,im_id,obj_id,source,depth_fit,note"

ImageKey = tuple[int, int]  # (scene_id, im_id)


@dataclass(frozen=True)
class RunSummary:
    """What one ``popcode run`` did."""

    images_done: int  # estimated in this call
    images_resumed: int  # already done by an earlier, interrupted call
    estimates: int  # lines written in this call
    skipped: dict[int, int]  # object id -> detections no model knows
    seconds: float
    sources: dict[str, int]  # translation source -> estimates of this call that took their translation from it


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (a resumed run must use the same models and detections); a FIFO or a device, whose
    read would never end, is refused."""
    if not path.is_file():
        raise PopcodeError(f"{path} is not a regular file (a FIFO or a device, say); replace it with a file")
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def model_digest(path: Path) -> str:
    """SHA-256 of a model and of the weights it keeps in other files (ONNX external data): the files in its folder,
    two levels down, whose relative path the model names (a location is stored as plain text in the model)."""
    data = path.read_bytes()
    digest = hashlib.sha256(data)
    folder = path.resolve().parent
    nearby = (found for pattern in ("*", "*/*") for found in folder.glob(pattern))
    candidates = sorted(found for found in islice(nearby, MAX_WEIGHT_FILES) if found.is_file())
    for candidate in candidates:
        name = candidate.relative_to(folder).as_posix()
        if candidate != path.resolve() and name.encode() in data:
            digest.update(f"\n{name}\n{file_digest(candidate)}".encode())
    return digest.hexdigest()


def split_digest(images: Mapping[ImageKey, SplitImage], depth: bool = False) -> str:
    """SHA-256 of what a split gives a run: each image's file name, size and modification time (``depth``: its depth
    image's too), and every scene's annotation files (cameras, boxes) by content. Cheap (one stat per image), and
    another split or an image changed in place, even to the same size, is told apart (a copy that keeps the times,
    ``cp -p`` or ``rsync -a``, still resumes)."""
    digest = hashlib.sha256()
    for key in sorted(images):
        paths = [images[key].path] + ([images[key].depth_path] if depth and images[key].depth_path else [])
        for path in paths:
            status = path.stat()
            digest.update(f"{key} {path.name} {status.st_size} {status.st_mtime_ns}\n".encode())
    for scene in sorted({images[key].path.parent.parent for key in images}):
        for annotation in sorted(scene.glob("*.json")):
            digest.update(f"{scene.name}/{annotation.name} {file_digest(annotation)}\n".encode())
    return digest.hexdigest()


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

    Opening it keeps every closed image (a torn tail from a killed run is dropped) and refuses a file made from
    other models, detections, split or options, one whose closed images were edited, and a second run writing the
    same ``out``. ``expected`` (image -> the object ids of its detections, in order) checks each kept image's
    lines against what this run would write for it. A finished ``out`` is replaced only with ``overwrite``.
    """

    def __init__(self, out: Path, fingerprint: str, expected: Mapping[ImageKey, Sequence[int]],
                 overwrite: bool = False) -> None:
        self.out, self.fingerprint = out, fingerprint
        self.path, lock, self.sources = companion_paths(out)
        self._lock = _OutputLock(lock)
        try:
            if not self.path.exists():  # a finished run's files; with a partial beside them, a rerun that resumes
                refuse_existing(out, "--out", overwrite)
                refuse_existing(self.sources, "--out's translation sources", overwrite)
            self.blocks: dict[ImageKey, list[str]] = {}  # each closed image's lines, its closing mark last
            if self.path.exists():
                self._resume(fingerprint, expected)
            lines = [line for block in self.blocks.values() for line in block]
            write_bytes_atomic(self.path, "\n".join([RUN_MARK + fingerprint, *lines]).encode() + b"\n")
            self._handle = self.path.open("a")
        except BaseException:
            self._lock.release()
            raise

    @property
    def done(self) -> Collection[ImageKey]:
        """The images closed so far."""
        return self.blocks.keys()

    def _refuse(self, why: str) -> PopcodeError:
        return PopcodeError(f"{self.path} {why}; remove it to start again, or rerun the command that made it")

    def _resume(self, fingerprint: str, expected: Mapping[ImageKey, Sequence[int]]) -> None:
        if not self.path.is_file():  # a FIFO would block the read forever, /dev/zero never end it
            raise self._refuse("is not a regular file")
        # at most an estimate and a translation line per detection and a closing mark per image, and the header
        limit = MAX_PARTIAL_LINE_BYTES * (2 * sum(len(ids) for ids in expected.values()) + len(expected) + 1)
        with self.path.open("rb") as handle:
            data = handle.read(limit + 1)
        if len(data) > limit:
            raise self._refuse(f"is larger than this run's results can be ({limit} bytes)")
        try:
            text = data.decode("utf-8").split("\n")
        except UnicodeDecodeError as error:
            raise self._refuse(f"is not text ({error.reason} at byte {error.start})") from error
        if text[0] != RUN_MARK + fingerprint:
            raise self._refuse("holds the partial results of a run with other models, detections, split or options")
        blocks: list[tuple[list[str], tuple[ImageKey, str] | None]] = []
        pending: list[str] = []
        for line in text[1:]:
            if line.startswith(DONE_MARK):
                blocks.append((pending, _done_key(line)))
                pending = []
            elif line:
                pending.append(line)  # lines after the last mark: an image a killed run did not close
        # A killed run can tear only its last image (lines, mark or both); anything wrong before that was changed.
        while blocks and _block_problem(*blocks[-1], expected, self.done, fingerprint) is not None:
            blocks.pop()
        for lines, mark in blocks:
            problem = _block_problem(lines, mark, expected, self.done, fingerprint)
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
        self._handle.flush()
        os.fsync(self._handle.fileno())
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
        self._handle.close()
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


class _OutputLock:
    """An exclusive lock on ``<out>.lock`` (POSIX ``flock``; the system drops it when the process ends, a kill
    too): of two runs writing one ``out``, the second is refused in one line."""

    def __init__(self, path: Path) -> None:
        self.path, self._handle = path, None
        if fcntl is None:  # no flock (Windows): runs are not guarded against each other
            return
        if path.exists() and not path.is_file():  # opening a FIFO would wait for a reader forever
            raise PopcodeError(f"{path} is not a regular file; remove it (popcode run keeps its lock there)")
        handle = path.open("a")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            handle.close()
            raise PopcodeError(f"another popcode run is writing {path.with_suffix('')} (it holds {path.name}); wait "
                               "for it or choose another --out") from error
        self._handle = handle

    def release(self) -> None:
        if self._handle is not None:
            self.path.unlink(missing_ok=True)  # while still held: a run that opens it later locks a new file
            self._handle.close()
            self._handle = None


class Progress:
    """One line on stderr: images done, rate and time left (redrawn in place on a terminal, every 10 % else)."""

    def __init__(self, total: int, enabled: bool = True) -> None:
        self.total, self.enabled, self.started = total, enabled and total > 0, time.perf_counter()
        self.tty, self.last_shown, self.count = sys.stderr.isatty(), -1.0, 0

    def step(self) -> None:
        self.count += 1
        if not self.enabled:
            return
        elapsed = time.perf_counter() - self.started
        due = elapsed - self.last_shown > 0.5 if self.tty else \
            self.count * 10 // self.total != (self.count - 1) * 10 // self.total
        if due or self.count == self.total:
            rate = self.count / max(elapsed, 1e-9)
            left = (self.total - self.count) / rate
            line = f"popcode run: {self.count}/{self.total} images, {rate:.1f} img/s, {left:.0f} s left"
            print(("\r" + line) if self.tty else line, end="\n" if not self.tty or self.count == self.total else "",
                  file=sys.stderr, flush=True)
            self.last_shown = elapsed


def _check_images(by_image: dict[ImageKey, list[Detection]], images: dict[ImageKey, SplitImage]) -> None:
    """Every detection's image exists in the split and has a camera (the translation needs it)."""
    missing = sorted(key for key in by_image if key not in images)
    if missing:
        scene_id, im_id = missing[0]
        raise PopcodeError(f"detections name {len(missing)} image(s) that are not in the split, first scene "
                           f"{scene_id} image {im_id}: wrong split or wrong detections file?")
    uncalibrated = sorted(key for key in by_image if images[key].K is None)
    if uncalibrated:
        scene_id, im_id = uncalibrated[0]
        more = f" (and {len(uncalibrated) - 1} more images)" if len(uncalibrated) > 1 else ""
        raise PopcodeError(f"scene {scene_id} image {im_id} has no cam_K in its scene_camera.json{more}: the "
                           "translation from the box needs the camera")


def _check_boxes(keys: Sequence[ImageKey], by_image: Mapping[ImageKey, Sequence[Detection]],
                 images: Mapping[ImageKey, SplitImage]) -> None:
    """Before any work: every box against its image's size, read from the file's header (an image whose header
    is not read here is checked when it is read)."""
    for key in keys:
        path = images[key].path
        try:  # a FIFO would block the open; unreadable files are named when the loop reads them
            size = image_size(path) if path.is_file() else None
        except OSError:
            size = None
        for detection in by_image[key] if size is not None else ():
            try:
                check_box(detection.box, (size[1], size[0]))
            except PopcodeError as error:
                raise PopcodeError(f"scene {key[0]} image {key[1]} ({path.name}), the detection of "
                                   f"object {detection.obj_id}: {error}") from error


def _check_depth(keys: Sequence[ImageKey], images: dict[ImageKey, SplitImage],
                 by_image: dict[ImageKey, list[Detection]], estimators: Sequence[PoseEstimator],
                 owner: Mapping[int, int], refine: bool) -> None:
    """Before any work: every image has a depth image, every model the surface points of its detected objects, and
    refinement its library."""
    lacking = [key for key in keys if images[key].depth_path is None]
    if lacking:
        scene_id, im_id = lacking[0]
        more = f" (and {len(lacking) - 1} more images)" if len(lacking) > 1 else ""
        raise PopcodeError(f"scene {scene_id} image {im_id} has no depth image in its depth/ folder{more}: --depth "
                           "reads each image's depth")
    for obj_id in sorted({d.obj_id for key in keys for d in by_image[key]}):
        estimators[owner[obj_id]].object_surface(obj_id)
    if refine:
        require_small_gicp()


def sources_path(out: Path) -> Path:
    """Where a run with depth says each estimate's translation source: ``<out stem>.translation<out suffix>``
    (``results.translation.csv``; ``results.translation`` for ``results``), one per results file."""
    return out.with_name(f"{out.stem}.translation{out.suffix}")


def companion_paths(out: Path) -> tuple[Path, Path, Path]:
    """The files a run writes beside ``out``: its partial results, its lock and its translation sources."""
    return out.with_name(out.name + PARTIAL_SUFFIX), out.with_name(out.name + LOCK_SUFFIX), sources_path(out)


def _source_lines(key: ImageKey, detections: Sequence[Detection], predictions: Sequence[Prediction]) -> list[str]:
    """One image's lines of the translation file (see the module docstring)."""
    rows = io.StringIO()
    writer = csv.writer(rows, lineterminator="\n")
    for d, p in zip(detections, predictions, strict=True):
        writer.writerow([key[0], key[1], d.obj_id, p.t_source, "" if p.depth_fit is None else f"{p.depth_fit:.4f}",
                         p.depth_note or ""])
    return rows.getvalue().splitlines()


def _estimates(key: ImageKey, detections: Sequence[Detection], predictions: Sequence[Prediction], detector_s: float,
               popcode_s: float) -> list[PoseEstimate]:
    """One image's results lines: score = detection score x calibrated confidence (where there is one)."""
    time_s = popcode_s + detector_s if detector_s >= 0 else popcode_s
    return [PoseEstimate(key[0], key[1], d.obj_id, d.score * (1.0 if p.confidence is None else p.confidence),
                         p.R_m2c, p.t_m2c_mm, time_s) for d, p in zip(detections, predictions, strict=True)]


def picture_path(draw_dir: Path, key: ImageKey) -> Path:
    """Where ``--draw`` puts an image's picture."""
    return draw_dir / f"{key[0]:06d}_{key[1]:06d}.png"


def draw_image(path: Path, image: np.ndarray, split_image: SplitImage,
               drawn: Sequence[tuple[PoseEstimator, list[Prediction]]]) -> None:
    """Every model's estimates of one image in one picture."""
    picture = image
    for estimator, predictions in drawn:
        picture = draw_predictions(picture, predictions, estimator.metadata, split_image.K)[..., ::-1]  # RGB
    write_picture_atomic(path, np.ascontiguousarray(picture[..., ::-1]))


def run_detections(estimators: Sequence[PoseEstimator], names: Sequence[str], images: dict[ImageKey, SplitImage],
                   detections: Sequence[Detection], out: Path, fingerprint: str, max_images: int | None = None,
                   progress: bool = True, draw_dir: Path | None = None, depth: bool = False,
                   refine: bool = False, overwrite: bool = False, inputs: Sequence[Path] = ()) -> RunSummary:
    """Estimate every detection whose object a model knows; write ``out`` (BOP19 CSV). See the module docstring.

    ``draw_dir``: also a picture of each image's estimates there (``<scene_id>_<im_id>.png``). ``depth``: the
    translation from each image's depth image, and ``refine`` (with depth): the pose refined against it.
    ``overwrite``: replace a finished ``out`` and, in a run that does not resume, pictures in ``draw_dir``; a
    picture is never one of the run's ``inputs`` (files or folders) nor its own output files.
    """
    started = time.perf_counter()
    owner = route_objects(estimators, names)
    skipped = Counter(d.obj_id for d in detections if d.obj_id not in owner)
    by_image: dict[ImageKey, list[Detection]] = defaultdict(list)
    # model by model (stable): an image's estimates are written in the order of the models
    for detection in sorted((d for d in detections if d.obj_id in owner), key=lambda d: owner[d.obj_id]):
        by_image[detection.image_key].append(detection)
    if detections and not by_image:
        raise PopcodeError(f"none of the {len(detections)} detections is of an object these models know (detected: "
                           f"objects {', '.join(map(str, sorted(skipped)[:10]))}; the models know objects "
                           f"{', '.join(map(str, sorted(owner)))}): wrong models or wrong detections file?")
    _check_images(by_image, images)
    keys = sorted(by_image)[:max_images]
    _check_boxes(keys, by_image, images)
    if depth:
        _check_depth(keys, images, by_image, estimators, owner, refine)
    if draw_dir is not None:  # never an input nor this run's own files; a resumed run finds its earlier pictures
        resuming, never = companion_paths(out)[0].exists(), [*inputs, out, *companion_paths(out)]
        for key in keys:
            check_output_file(picture_path(draw_dir, key), "--draw picture", never, overwrite or resuming)
    results = PartialResults(out, fingerprint, {key: [d.obj_id for d in by_image[key]] for key in keys}, overwrite)
    try:
        todo = [key for key in keys if key not in results.done]
        bar, written, sources = Progress(len(todo), progress), 0, Counter()
        work = (ImageBoxes(key, images[key].path, images[key].K, [d.box for d in by_image[key]],
                           [d.obj_id for d in by_image[key]], images[key].depth_path if depth else None,
                           images[key].depth_scale) for key in todo)
        for done in estimate_images(estimators, names, work, translation=True, refine_depth=depth and refine):
            key, chosen = done.key, by_image[done.key]
            detector_s = max(d.time_s for d in chosen)
            estimates = _estimates(key, chosen, done.predictions, detector_s, done.seconds)
            if draw_dir is not None:  # before the image is closed: a resume redraws what a kill left undrawn
                draw_image(picture_path(draw_dir, key), done.image, images[key], done.by_model)
            results.add(key, estimates, _source_lines(key, chosen, done.predictions) if depth else ())
            sources.update(str(p.t_source) for p in done.predictions)
            written += len(estimates)
            bar.step()
        results.finish()
    finally:
        results.close()
    return RunSummary(len(todo), len(keys) - len(todo), written, dict(sorted(skipped.items())),
                      time.perf_counter() - started, dict(sorted(sources.items())))
