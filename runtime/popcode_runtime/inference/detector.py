"""``Detector``: a popcode detector's ONNX file behind one call, camera frame -> every part's box, object and score.

The network gives a score per object and a box for every place of its
feature maps (docs/design.md#detector-contract); here a frame of any size and
aspect is letterboxed into the detector's input (:func:`detector_input`, which
the trainer's data uses too), the places scoring below the threshold are
dropped, OpenCV's non-maximum suppression keeps, per object, the best of
overlapping boxes, and the boxes are mapped back to the frame. A frame with no
parts gives an empty list.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..base.checks import path
from ..base.errors import PopcodeError, library_step
from ..geometry.crop import to_grey
from ..geometry.letterbox import Letterbox
from ..model.detector_metadata import (
    DETECTOR_BOXES,
    DETECTOR_INPUT,
    DETECTOR_INPUT_MEAN,
    DETECTOR_SCORES,
    PREFIX,
    DetectorMetadata,
)
from ..model.engine import custom_metadata, onnx_session

MAX_CANDIDATES = 5000  # places above the threshold that go to NMS, best first: bounds its quadratic work


@dataclass(frozen=True)
class DetectedBox:
    """One part the detector found: its object id, box ``(x, y, w, h)`` in the frame's pixels and score in [0, 1]."""

    obj_id: int
    box: tuple[float, float, float, float]
    score: float

    def to_dict(self) -> dict[str, object]:
        return {"obj_id": self.obj_id, "box": list(self.box), "score": self.score}


def is_detector_file(model_path: str | Path) -> bool:
    """Whether an ONNX file carries a popcode detector's metadata (rather than a pose model's, or none)."""
    model_path = path(model_path, "model path")
    return f"{PREFIX}format_version" in custom_metadata(onnx_session(model_path, None, 1), model_path)


def detector_input(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """A frame as the detector sees it: grey float32 ``(height, width)`` in [0, 1], letterboxed (:class:`Letterbox`:
    resized, area-averaged when shrinking, the rest of the input ``DETECTOR_INPUT_MEAN``).

    The one path from a frame to the detector, for every entry point and the trainer's frames: the frame is made
    grey float first (:func:`to_grey`), so a frame as stored (8- or 16-bit) and the float frame ``read_image``
    gives of it are the same pixels to the detector. The pad is the grey the graph normalises to 0, what its
    convolutions see beyond the input's border anyway: neutral to the network, the same for every frame (nothing
    to compute), and a frame of only that grey finds no part where a black one did (bench/results/frame-path.md).
    """
    grey = to_grey(image)
    fit = Letterbox.fit((grey.shape[1], grey.shape[0]), (width, height))
    shrink = fit.scaled[0] < grey.shape[1]
    resized = cv2.resize(grey, fit.scaled, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
    np.clip(resized, 0.0, 1.0, out=resized)  # an average of values in [0, 1] may round a hair past them
    if fit.scaled == (width, height):
        return resized
    frame = np.full((height, width), DETECTOR_INPUT_MEAN, np.float32)
    (x, y), (cols, rows) = fit.offset, fit.scaled
    frame[y:y + rows, x:x + cols] = resized
    return frame


class Detector:
    """``detect(image)`` -> :class:`DetectedBox` list, best first; thresholds from the file unless given here."""

    def __init__(self, model_path: str | Path, providers: Sequence[str] | None = None, threads: int = 0,
                 score_threshold: float | None = None, nms_iou: float | None = None,
                 max_detections: int | None = None) -> None:
        self.model_path = path(model_path, "detector path")
        self.session = onnx_session(self.model_path, providers, threads)
        try:
            self.metadata = DetectorMetadata.from_props(custom_metadata(self.session, self.model_path))
            self._check_signature()
        except PopcodeError as error:
            raise PopcodeError(f"{self.model_path}: {error}") from error
        meta = self.metadata
        self.score_threshold = meta.score_threshold if score_threshold is None else score_threshold
        self.nms_iou = meta.nms_iou if nms_iou is None else nms_iou
        self.max_detections = meta.max_detections if max_detections is None else max_detections
        DetectorMetadata.check_thresholds(self.score_threshold, self.nms_iou, self.max_detections)
        self.last_seconds = 0.0  # the last detect call, resize to boxes

    def _check_signature(self) -> None:
        meta = self.metadata
        inputs = {i.name: i for i in self.session.get_inputs()}
        outputs = {o.name: o for o in self.session.get_outputs()}
        if set(inputs) != {DETECTOR_INPUT}:
            raise PopcodeError(f"a detector has one input named '{DETECTOR_INPUT}', this one has {sorted(inputs)}")
        shape = inputs[DETECTOR_INPUT].shape
        if list(shape) != [1, 1, meta.input_height, meta.input_width]:
            raise PopcodeError(f"input '{DETECTOR_INPUT}' must be [1, 1, {meta.input_height}, {meta.input_width}] "
                               f"as its metadata says, the graph declares {shape}")
        missing = {DETECTOR_BOXES, DETECTOR_SCORES} - set(outputs)
        if missing:
            raise PopcodeError(f"a detector has outputs '{DETECTOR_BOXES}' and '{DETECTOR_SCORES}'; this one lacks "
                               f"{sorted(missing)}")
        classes = outputs[DETECTOR_SCORES].shape[-1]
        if isinstance(classes, int) and classes != len(meta.obj_ids):
            raise PopcodeError(f"output '{DETECTOR_SCORES}' has {classes} columns for the {len(meta.obj_ids)} object "
                               "ids of the metadata")

    @property
    def obj_ids(self) -> tuple[int, ...]:
        return self.metadata.obj_ids

    def detect(self, image: np.ndarray) -> list[DetectedBox]:
        """Every part found in ``image`` (grey or RGB, uint8/uint16 or float in [0, 1]), best score first."""
        started = time.perf_counter()
        meta = self.metadata
        frame = detector_input(image, meta.input_width, meta.input_height)
        with library_step(f"run the detector {self.model_path}"):
            boxes, scores = self.session.run([DETECTOR_BOXES, DETECTOR_SCORES], {DETECTOR_INPUT: frame[None, None]})
        found = self._select(np.asarray(boxes, np.float32)[0], np.asarray(scores, np.float32)[0], image.shape)
        self.last_seconds = time.perf_counter() - started
        return found

    def _select(self, boxes: np.ndarray, scores: np.ndarray, image_shape: tuple[int, ...]) -> list[DetectedBox]:
        """Threshold, per-object NMS and the cap, then boxes in the frame's pixels (the letterbox undone, clipped to
        the frame)."""
        if boxes.ndim != 2 or boxes.shape[1] != 4 or scores.shape != (len(boxes), len(self.obj_ids)):
            raise PopcodeError(f"the detector returned boxes {boxes.shape} and scores {scores.shape}; expected (L, 4) "
                               f"and (L, {len(self.obj_ids)})")
        scores = np.nan_to_num(scores, nan=0.0)
        places, classes = np.nonzero(scores >= self.score_threshold)
        values = scores[places, classes]
        if len(values) > MAX_CANDIDATES:
            best = np.argpartition(-values, MAX_CANDIDATES)[:MAX_CANDIDATES]
            places, classes, values = places[best], classes[best], values[best]
        rows, cols = image_shape[:2]
        fit = Letterbox.fit((cols, rows), (self.metadata.input_width, self.metadata.input_height))
        edges = fit.to_frame(np.nan_to_num(boxes[places]))
        xywh = np.column_stack([edges[:, :2], edges[:, 2:] - edges[:, :2]])
        usable = (xywh[:, 2] >= 1.0) & (xywh[:, 3] >= 1.0)
        xywh, classes, values = xywh[usable], classes[usable], values[usable]
        if not len(values):
            return []
        with library_step("suppress overlapping boxes with OpenCV"):  # top_k 0: OpenCV's would cut the candidates
            kept = cv2.dnn.NMSBoxesBatched(xywh.tolist(), values.tolist(), classes.tolist(), self.score_threshold,
                                           self.nms_iou)
        kept = sorted(np.asarray(kept, int).reshape(-1).tolist(), key=lambda i: -values[i])[: self.max_detections]
        return [DetectedBox(self.obj_ids[classes[i]], tuple(float(v) for v in xywh[i]), float(values[i]))
                for i in kept]
