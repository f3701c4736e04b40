"""``popcode run``'s loop: a pose for every detection of a BOP split, into the resumable results file.

popcode is the pose stage after any 2-D detector: each image is read once, the
boxes of each model go through it in one batch
(:mod:`popcode_runtime.inference.image_loop`), the translation is fitted to
each box with the image's ``cam_K`` (or read from its depth image), and the
image's estimates go to the results file (:mod:`.run_results`). Everything a
run can find wrong in its inputs is checked before the first image. The
``time`` of an image is the measured seconds of popcode's work on it (read,
crop, network, decode, translation) plus the detector's own time when the
detections give one; the ``score`` is the detection score times the calibrated
confidence where the model has a calibrator.
"""

from __future__ import annotations

import csv
import io
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..base.errors import PopcodeError
from ..base.files import check_output_file, write_picture_atomic
from ..base.image_size import image_size
from ..bop.bop19_csv import PoseEstimate
from ..bop.detections import Detection
from ..bop.split import SplitImage
from ..depth.icp import require_small_gicp
from ..geometry.camera import camera_for_image
from ..geometry.crop import check_box
from ..inference.estimator import PoseEstimator
from ..inference.image_loop import ImageBoxes, estimate_images, route_objects
from ..inference.prediction import Prediction
from .drawing import draw_models
from .run_results import ImageKey, PartialResults, companion_paths


@dataclass(frozen=True)
class RunSummary:
    """What one ``popcode run`` did."""

    images_done: int  # estimated in this call
    images_resumed: int  # already done by an earlier, interrupted call
    estimates: int  # lines written in this call
    skipped: dict[int, int]  # object id -> detections no model knows
    seconds: float
    sources: dict[str, int]  # translation source -> estimates of this call that took their translation from it


class Progress:
    """One line on stderr: images done, rate and time left (redrawn in place on a terminal, every 10 % else)."""

    def __init__(self, total: int, enabled: bool = True, label: str = "popcode run") -> None:
        self.total, self.enabled, self.started = total, enabled and total > 0, time.perf_counter()
        self.label = label
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
            line = f"{self.label}: {self.count}/{self.total} images, {rate:.1f} img/s, {left:.0f} s left"
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
    _refuse_first(sorted(key for key in by_image if images[key].K is None),
                  "has no cam_K in its scene_camera.json{more}: the translation from the box needs the camera")


def _refuse_first(keys: Sequence[ImageKey], problem: str) -> None:
    """Refuse the first of ``keys``, the images that have ``problem`` (``{more}`` in it counts the others)."""
    if keys:
        more = f" (and {len(keys) - 1} more images)" if len(keys) > 1 else ""
        raise PopcodeError(f"scene {keys[0][0]} image {keys[0][1]} {problem.format(more=more)}")


def _check_image_sizes(keys: Sequence[ImageKey], by_image: Mapping[ImageKey, Sequence[Detection]],
                       images: Mapping[ImageKey, SplitImage]) -> None:
    """Before any work: every camera and box against its image's size, read from the file's header (an image
    whose header is not read here is checked when it is read). A split's image is the whole frame its cam_K
    belongs to."""
    for key in keys:
        path = images[key].path
        try:  # a FIFO would block the open; unreadable files are named when the loop reads them
            size = image_size(path) if path.is_file() else None
        except OSError:
            size = None
        if size is None:
            continue
        where = f"scene {key[0]} image {key[1]} ({path.name})"
        try:
            camera_for_image(images[key].K, (size[1], size[0]))
        except PopcodeError as error:
            raise PopcodeError(f"{where}, its cam_K in scene_camera.json: {error}") from error
        for detection in by_image[key]:
            try:
                check_box(detection.box, (size[1], size[0]))
            except PopcodeError as error:
                raise PopcodeError(f"{where}, the detection of object {detection.obj_id}: {error}") from error


def _check_depth(keys: Sequence[ImageKey], images: dict[ImageKey, SplitImage],
                 by_image: dict[ImageKey, list[Detection]], estimators: Sequence[PoseEstimator],
                 owner: Mapping[int, int], refine: bool) -> None:
    """Before any work: every image has a depth image and its depth_scale, every model the surface points of its
    detected objects, and refinement its library.

    A missing depth_scale is refused, not taken as 1: BOP's format gives it in scene_camera.json for every split
    with depth, the datasets' units differ (0.1 mm for T-LESS, 1 mm for LM), and a wrong one would send every
    instance back to the box's translation with a note that does not say why.
    """
    _refuse_first([key for key in keys if images[key].depth_path is None],
                  "has no depth image in its depth/ folder{more}: --depth reads each image's depth")
    _refuse_first([key for key in keys if images[key].depth_scale is None],
                  "has no 'depth_scale' in its scene_camera.json entry{more}: --depth needs the mm per depth unit "
                  "there, as BOP's format gives it")
    for obj_id in sorted({d.obj_id for key in keys for d in by_image[key]}):
        estimators[owner[obj_id]].object_surface(obj_id)
    if refine:
        require_small_gicp()


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
    write_picture_atomic(path, draw_models(image, [(e.metadata, found) for e, found in drawn], split_image.K))


def check_pictures(draw_dir: Path, keys: Sequence[ImageKey], out: Path, inputs: Sequence[Path],
                   overwrite: bool) -> None:
    """The pictures ``--draw`` would write of ``keys``: never an input nor the run's own files; one that exists is
    replaced only with ``overwrite`` or by a run that resumes (it finds its earlier pictures)."""
    resuming, never = companion_paths(out)[0].exists(), [*inputs, out, *companion_paths(out)]
    for key in keys:
        check_output_file(picture_path(draw_dir, key), "--draw picture", never, overwrite or resuming)


def run_detections(estimators: Sequence[PoseEstimator], names: Sequence[str], images: dict[ImageKey, SplitImage],
                   detections: Sequence[Detection], *, out: Path, fingerprint: str, max_images: int | None = None,
                   progress: bool = True, draw_dir: Path | None = None, depth: bool = False,
                   refine: bool = False, overwrite: bool = False, inputs: Sequence[Path] = (),
                   results: PartialResults | None = None) -> RunSummary:
    """Estimate every detection whose object a model (``names``: their files) knows; write ``out`` (BOP19 CSV).

    ``fingerprint``: what the results depend on (:mod:`.run_fingerprint`). ``max_images``: only the first images
    with detections. ``draw_dir``: also a picture of each image's estimates there (``<scene_id>_<im_id>.png``).
    ``depth``: the translation from each image's depth image, and ``refine`` (with depth): the pose refined against
    it. ``overwrite``: replace a finished ``out`` and, in a run that does not resume, pictures in ``draw_dir``; a
    picture is never one of the run's ``inputs`` (files or folders) nor its own output files. ``results``: ``out``'s
    partial results, claimed by a caller that had work to do first (a detector's run); closed when this returns.
    """
    started = time.perf_counter()
    with results or PartialResults(out, fingerprint, overwrite) as results:  # closed (lock released) however it ends
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
        _check_image_sizes(keys, by_image, images)
        if depth:
            _check_depth(keys, images, by_image, estimators, owner, refine)
        if draw_dir is not None:
            check_pictures(draw_dir, keys, out, inputs, overwrite)
        results.resume({key: [d.obj_id for d in by_image[key]] for key in keys})
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
        return RunSummary(len(todo), len(keys) - len(todo), written, dict(sorted(skipped.items())),
                          time.perf_counter() - started, dict(sorted(sources.items())))
