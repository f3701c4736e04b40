"""``popcode run``: a pose for every detection of a BOP split, written as a BOP19 results file.

popcode is the pose stage after any 2-D detector: each image is read once, the
boxes of each model go through it in one batch (:mod:`.image_loop`), the
translation is fitted to each box with the image's ``cam_K``, and the
image's estimates are appended to ``<out>.partial`` with a closing mark. A run
that is stopped resumes from the last closed image; the results file appears
(atomically) only when every image is done. The ``time`` of an image is the
measured seconds of popcode's work on it (read, crop, network, decode,
translation) plus the detector's own time when the detections give one; the
``score`` is the detection score times the calibrated confidence where the
model has a calibrator.
"""

from __future__ import annotations

import hashlib
import os
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .bop19_csv import PoseEstimate, format_estimate, write_bop19_lines
from .bop_split import SplitImage, name_id
from .detections import Detection
from .drawing import draw_predictions
from .errors import PopcodeError
from .estimator import PoseEstimator, Prediction
from .files import write_bytes_atomic, write_picture_atomic
from .image_loop import ImageBoxes, estimate_images, route_objects

PARTIAL_SUFFIX = ".partial"
RUN_MARK = "#popcode-run "  # first line of a partial file: what the run was made from
DONE_MARK = "#done "  # closes one image's estimates

ImageKey = tuple[int, int]  # (scene_id, im_id)


@dataclass(frozen=True)
class RunSummary:
    """What one ``popcode run`` did."""

    images_done: int  # estimated in this call
    images_resumed: int  # already done by an earlier, interrupted call
    estimates: int  # lines written in this call
    skipped: dict[int, int]  # object id -> detections no model knows
    seconds: float


def file_digest(path: Path) -> str:
    """SHA-256 of a file's bytes (a resumed run must use the same models and detections)."""
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _done_key(line: str) -> ImageKey | None:
    """The image a whole ``#done scene_id im_id`` line closes; None for any other line (a torn mark too)."""
    ids = [name_id(field) for field in line[len(DONE_MARK):].split()] if line.startswith(DONE_MARK) else []
    return (ids[0], ids[1]) if len(ids) == 2 and None not in ids else None


class PartialResults:
    """``<out>.partial``: the estimate lines of finished images, each image closed by a ``#done`` line.

    Opening it keeps every closed image (a torn tail from a killed run is
    dropped) and refuses a file made from other models, detections or options.
    """

    def __init__(self, out: Path, fingerprint: str) -> None:
        self.out, self.path = out, out.with_name(out.name + PARTIAL_SUFFIX)
        if out.exists() and not self.path.exists():
            raise PopcodeError(f"{out} exists already (a finished run); remove it or choose another --out")
        self.lines: list[str] = []
        self.done: set[ImageKey] = set()
        if self.path.exists():
            self._resume(fingerprint)
        write_bytes_atomic(self.path, "\n".join([RUN_MARK + fingerprint, *self.lines]).encode() + b"\n")
        self._handle = self.path.open("a")

    def _resume(self, fingerprint: str) -> None:
        text = self.path.read_text(errors="replace").split("\n")
        if not text or text[0] != RUN_MARK + fingerprint:
            raise PopcodeError(f"{self.path} holds the partial results of a run with other models, detections or "
                               "options; remove it to start again, or rerun the command that made it")
        pending: list[str] = []
        for line in text[1:]:
            key = _done_key(line)
            if key is not None:
                self.lines += [*pending, line]
                self.done.add(key)
                pending = []
            elif line:
                pending.append(line)  # lines of an image that was not closed (or a torn mark) are dropped

    def add(self, key: ImageKey, estimates: Sequence[PoseEstimate]) -> None:
        """Append one image's estimates and its closing mark, flushed to disk."""
        lines = [format_estimate(est) for est in estimates] + [f"{DONE_MARK}{key[0]} {key[1]}"]
        self._handle.write("\n".join(lines) + "\n")
        self._handle.flush()
        os.fsync(self._handle.fileno())
        self.lines += lines
        self.done.add(key)

    def finish(self) -> None:
        """Write the results file (header and every estimate) atomically and remove the partial file."""
        self._handle.close()
        write_bop19_lines(self.out, [line for line in self.lines if not line.startswith("#")])
        self.path.unlink()

    def close(self) -> None:
        self._handle.close()


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


def _estimates(key: ImageKey, detections: Sequence[Detection], predictions: Sequence[Prediction], detector_s: float,
               popcode_s: float) -> list[PoseEstimate]:
    """One image's results lines: score = detection score x calibrated confidence (where there is one)."""
    time_s = popcode_s + detector_s if detector_s >= 0 else popcode_s
    return [PoseEstimate(key[0], key[1], d.obj_id, d.score * (1.0 if p.confidence is None else p.confidence),
                         p.R_m2c, p.t_m2c_mm, time_s) for d, p in zip(detections, predictions, strict=True)]


def draw_image(path: Path, image: np.ndarray, split_image: SplitImage,
               drawn: Sequence[tuple[PoseEstimator, list[Prediction]]]) -> None:
    """Every model's estimates of one image in one picture."""
    picture = image
    for estimator, predictions in drawn:
        picture = draw_predictions(picture, predictions, estimator.metadata, split_image.K)[..., ::-1]  # RGB
    write_picture_atomic(path, np.ascontiguousarray(picture[..., ::-1]))


def run_detections(estimators: Sequence[PoseEstimator], names: Sequence[str], images: dict[ImageKey, SplitImage],
                   detections: Sequence[Detection], out: Path, fingerprint: str, max_images: int | None = None,
                   progress: bool = True, draw_dir: Path | None = None) -> RunSummary:
    """Estimate every detection whose object a model knows; write ``out`` (BOP19 CSV). See the module docstring.

    ``draw_dir``: also a picture of each image's estimates there (``<scene_id>_<im_id>.png``).
    """
    started = time.perf_counter()
    owner = route_objects(estimators, names)
    skipped = Counter(d.obj_id for d in detections if d.obj_id not in owner)
    by_image: dict[ImageKey, list[Detection]] = defaultdict(list)
    # model by model (stable): an image's estimates are written in the order of the models
    for detection in sorted((d for d in detections if d.obj_id in owner), key=lambda d: owner[d.obj_id]):
        by_image[detection.image_key].append(detection)
    _check_images(by_image, images)
    keys = sorted(by_image)[:max_images]
    results = PartialResults(out, fingerprint)
    try:
        todo = [key for key in keys if key not in results.done]
        bar, written = Progress(len(todo), progress), 0
        work = (ImageBoxes(key, images[key].path, images[key].K, [d.box for d in by_image[key]],
                           [d.obj_id for d in by_image[key]]) for key in todo)
        for done in estimate_images(estimators, names, work, translation=True):
            key, chosen = done.key, by_image[done.key]
            detector_s = max(d.time_s for d in chosen)
            estimates = _estimates(key, chosen, done.predictions, detector_s, done.seconds)
            results.add(key, estimates)
            written += len(estimates)
            if draw_dir is not None:
                draw_image(draw_dir / f"{key[0]:06d}_{key[1]:06d}.png", done.image, images[key], done.by_model)
            bar.step()
        results.finish()
    finally:
        results.close()
    return RunSummary(len(todo), len(keys) - len(todo), written, dict(sorted(skipped.items())),
                      time.perf_counter() - started)
