"""One frame path (issue 62): whichever entry point reads a frame -- ``popcode detect`` (an image or a split),
``popcode run --detector``, ``popcode predict --detector``, ``FramePoseEstimator`` -- the shipped detector sees
the same pixels, 8- or 16-bit, and a frame of any aspect is letterboxed into its input and its boxes mapped back
exactly."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from popcode_runtime import Detector, FramePoseEstimator, read_image
from popcode_runtime.commands.cli import main
from popcode_runtime.geometry.crop import read_image_file, to_grey
from popcode_runtime.geometry.letterbox import Letterbox
from popcode_runtime.model.detector_metadata import DETECTOR_INPUT_MEAN, MAX_DETECTIONS

MODELS = Path(__file__).resolve().parents[2] / "models"
DETECTOR = MODELS / "builtin-parts-detector.onnx"
POSE_MODEL = MODELS / "builtin-parts-3-6.onnx"  # one model: the boxes are what is compared, loading is slow
BIN = MODELS / "samples" / "bin.png"  # 720 x 540, 8-bit grey: the detector's own aspect
FOCAL_PX = 864.0
# The best boxes each entry point poses: the pose models' work is most of the test's time, and the boxes of two
# ways of resizing differed in every box, the best ones too (by up to half a pixel), not only in how many there were.
BEST = 5
CANVAS_GREY = 200  # the surroundings of the bin in the frames of other aspects: not the letterbox's pad grey
# Where the bin lies in each frame of another aspect, and that frame's size (columns, rows). The offsets are
# whole multiples of the source pixels per detector-input pixel (3.75 and 5), so that the hand-padded 4:3
# references below are resampled on the same grid as the letterboxed frames.
CANVASES = {"16:9": ((120, 0), (960, 540)), "portrait": ((0, 210), (720, 960))}


def _bin() -> np.ndarray:
    return cv2.imread(str(BIN), cv2.IMREAD_UNCHANGED)


def _canvas(name: str) -> np.ndarray:
    (x, y), (cols, rows) = CANVASES[name]
    frame = np.full((rows, cols), CANVAS_GREY, np.uint8)
    frame[y:y + 540, x:x + 720] = _bin()
    return frame


FRAMES = {
    "8-bit": _bin,
    "16-bit": lambda: _bin().astype(np.uint16) * 257,  # the same values: v / 255 == 257 v / 65535
    "16:9": lambda: _canvas("16:9"),
    "portrait-16-bit": lambda: _canvas("portrait").astype(np.uint16) * 257,
}


def _boxes(found) -> list[tuple[int, tuple[float, ...], float]]:
    return [(d.obj_id, d.box, d.score) for d in found]


@pytest.fixture()
def seen(monkeypatch):
    """The boxes of every ``Detector.detect`` call, in call order."""
    calls: list[list] = []
    detect = Detector.detect

    def recording(self, image):
        found = detect(self, image)
        calls.append(_boxes(found))
        return found

    monkeypatch.setattr(Detector, "detect", recording)
    return calls


@pytest.mark.parametrize("name", FRAMES)
def test_every_entry_point_gives_the_same_boxes(name, seen, tmp_path, capsys):
    frame = FRAMES[name]()
    rows, cols = frame.shape
    K = [FOCAL_PX, FOCAL_PX, (cols - 1) / 2, (rows - 1) / 2]
    scene = tmp_path / "split" / "000000"
    (scene / "gray").mkdir(parents=True)
    image = scene / "gray" / "000000.png"
    assert cv2.imwrite(str(image), frame)
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [K[0], 0, K[2], 0, K[1], K[3], 0, 0, 1],
                                                               "depth_scale": 1.0}}))
    model, split = str(POSE_MODEL), str(tmp_path / "split")
    cap = ["--max-detections", str(BEST)]
    assert main(["detect", str(DETECTOR), str(image), "--json", *cap]) == 0
    assert main(["detect", str(DETECTOR), "--split", split, "--out", str(tmp_path / "d.json"), "--quiet", *cap]) == 0
    assert main(["run", model, "--split", split, "--detector", str(DETECTOR), "--out", str(tmp_path / "r.csv"),
                 "--quiet", *cap]) == 0
    assert main(["predict", model, str(image), "--detector", str(DETECTOR), "--K", ",".join(map(str, K)), "--json",
                 *cap]) == 0
    FramePoseEstimator.from_files(DETECTOR, [POSE_MODEL], max_detections=BEST).estimate(read_image(image), K=K)
    capsys.readouterr()
    assert len(seen) == 5 and len(seen[0]) == BEST
    assert all(boxes == seen[0] for boxes in seen)
    if name in ("8-bit", "16-bit"):  # and the 8- and 16-bit files give the boxes of the frame as the file stores it
        assert seen[0] == _boxes(Detector(DETECTOR, max_detections=BEST).detect(read_image_file(BIN)))


@pytest.mark.parametrize("name", CANVASES)
def test_a_frame_of_another_aspect_is_letterboxed_and_its_boxes_mapped_back(name):
    """The shipped detector on a 16:9 and a portrait frame gives the boxes of the same frame padded to 4:3 by hand
    (with the letterbox's grey), less the padding: the detector saw the same pixels, the boxes came back by
    removing the offset and dividing by the scale. The tolerance is float32 rounding: of the two mappings (a box's
    edges are near 1000 px, float32 resolves 1e-4 px there) and of the area average over the reference's pad.
    Without NMS (IoU 1): the runtime suppresses among boxes clipped to the frame, which a box that reaches into the
    pad changes, so only the thresholded boxes themselves map one to one."""
    frame = _canvas(name)
    rows, cols = frame.shape
    if cols * 3 > rows * 4:  # wider than 4:3: padded above and below
        pad = ((cols * 3 // 4 - rows) // 2, 0)
        padded = np.full((cols * 3 // 4, cols), DETECTOR_INPUT_MEAN, np.float32)
        padded[pad[0]:pad[0] + rows] = to_grey(frame)
    else:  # taller: padded left and right
        pad = (0, (rows * 4 // 3 - cols) // 2)
        padded = np.full((rows, rows * 4 // 3), DETECTOR_INPUT_MEAN, np.float32)
        padded[:, pad[1]:pad[1] + cols] = to_grey(frame)
    detector = Detector(DETECTOR, nms_iou=1.0, max_detections=MAX_DETECTIONS)
    found = detector.detect(frame)
    expected = []
    for d in detector.detect(padded):
        x0, y0 = max(d.box[0] - pad[1], 0.0), max(d.box[1] - pad[0], 0.0)
        x1, y1 = min(d.box[0] + d.box[2] - pad[1], cols), min(d.box[1] + d.box[3] - pad[0], rows)
        if x1 - x0 >= 1.0 and y1 - y0 >= 1.0:
            expected.append((d.obj_id, (x0, y0, x1 - x0, y1 - y0), d.score))
    assert len(found) >= 8 and [d.obj_id for d in found] == [obj_id for obj_id, _, _ in expected]
    assert np.allclose([d.score for d in found], [score for _, _, score in expected], atol=1e-6, rtol=0)
    assert np.allclose([d.box for d in found], [box for _, box, _ in expected], atol=1e-3, rtol=0)


@pytest.mark.parametrize(("frame", "scaled", "offset"), [
    ((1280, 720), (256, 144), (0, 24)),  # 16:9: the width fills the input, 24 rows of pad above and below
    ((540, 720), (144, 192), (56, 0)),  # 3:4 portrait: 56 columns of pad left and right
    ((720, 540), (256, 192), (0, 0)),  # the detector's own aspect: resized, no pad
    ((4000, 3), (256, 1), (0, 95)),  # a sliver keeps at least one row
])
def test_the_letterbox_fits_the_frame_and_maps_boxes_back_exactly(frame, scaled, offset):
    fit = Letterbox.fit(frame, (256, 192))
    assert (fit.scaled, fit.offset) == (scaled, offset)
    box = np.array([[1.0, 1.5, frame[0] - 1.0, frame[1] - 0.5]])
    assert np.allclose(fit.to_frame(fit.to_input(box)), box, atol=1e-9, rtol=0)
    # the whole input is the whole frame: the pad is cut off
    assert np.allclose(fit.to_frame(np.array([[0.0, 0.0, 256.0, 192.0]])), [[0, 0, *frame]], atol=1e-9, rtol=0)


def test_a_box_in_letterboxed_coordinates_maps_back_by_hand():
    """1280 x 720 into 256 x 192: scale 0.2, 24 rows of pad on top; a box in the pad is cut to the frame."""
    fit = Letterbox.fit((1280, 720), (256, 192))
    assert np.array_equal(fit.to_frame(np.array([[10.0, 34.0, 50.0, 74.0], [0.0, 0.0, 20.0, 30.0]])),
                          [[50.0, 50.0, 250.0, 250.0], [0.0, 0.0, 100.0, 30.0]])
    assert np.allclose(fit.to_input(np.array([[50.0, 50.0, 250.0, 250.0]])), [[10.0, 34.0, 50.0, 74.0]], atol=1e-9,
                       rtol=0)
