"""The runtime's Detector on real ONNX graphs of known outputs: thresholds, per-object NMS, scaling to the frame,
the frame's size and aspect, and every refusal in one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.crop import to_grey
from popcode_runtime.inference.detector import Detector, detector_input
from popcode_runtime.model.detector_metadata import DETECTOR_INPUT_MEAN, DetectorMetadata
from tests.onnx_models import fixed_detector, linear_model, save

MODELS = Path(__file__).resolve().parents[2] / "models"
WIDTH, HEIGHT = 64, 48
# Four places: two overlapping boxes of object 1 (NMS keeps the better), one of object 2 over the first (another
# object: kept), one of object 1 elsewhere below the threshold.
BOXES = np.array([[8, 8, 24, 24], [9, 9, 25, 25], [8, 8, 24, 24], [40, 20, 60, 40]], np.float32)
SCORES = np.array([[0.9, 0.0], [0.8, 0.0], [0.0, 0.7], [0.2, 0.0]], np.float32)


def _metadata(**changes: object) -> DetectorMetadata:
    return DetectorMetadata(**{"obj_ids": (1, 2), "input_width": WIDTH, "input_height": HEIGHT, **changes})


@pytest.fixture()
def detector_path(tmp_path):
    return save(fixed_detector(BOXES, SCORES, _metadata(), brightness_gate=True), tmp_path / "det.onnx")


def test_threshold_and_nms_per_object(detector_path):
    found = Detector(detector_path).detect(np.full((HEIGHT, WIDTH), 1.0, np.float32))
    assert [(d.obj_id, d.box) for d in found] == [(1, (8.0, 8.0, 16.0, 16.0)), (2, (8.0, 8.0, 16.0, 16.0))]
    assert found[0].score == pytest.approx(0.9) and found[1].score == pytest.approx(0.7)


def test_thresholds_given_by_the_caller_replace_the_files(detector_path):
    frame = np.full((HEIGHT, WIDTH), 1.0, np.float32)
    assert len(Detector(detector_path, score_threshold=0.1).detect(frame)) == 3  # the 0.2 box too
    assert len(Detector(detector_path, nms_iou=0.99).detect(frame)) == 3  # the two object-1 boxes both kept
    assert len(Detector(detector_path, max_detections=1).detect(frame)) == 1


def test_boxes_are_scaled_to_the_frame_and_clipped(detector_path):
    found = Detector(detector_path).detect(np.full((4 * HEIGHT, 4 * WIDTH), 255, np.uint8))
    assert found[0].box == (32.0, 32.0, 64.0, 64.0)
    edge = Detector(save(fixed_detector(np.array([[-10, -5, 20, 30]], np.float32), np.array([[0.9, 0.0]]),
                                        _metadata()), detector_path.parent / "edge.onnx"))
    assert edge.detect(np.zeros((HEIGHT, WIDTH), np.uint8))[0].box == (0.0, 0.0, 20.0, 30.0)


def test_a_frame_without_parts_gives_an_empty_list(detector_path):
    assert Detector(detector_path).detect(np.zeros((HEIGHT, WIDTH), np.uint8)) == []


def test_a_frame_of_another_aspect_is_letterboxed(detector_path):
    """A 64 x 64 frame in the 64 x 48 input: scaled by 0.75 to 48 x 48, 8 columns of pad either side; a box in
    the input comes back less the pad, divided by the scale, cut to the frame; one wholly in the pad is dropped."""
    boxes = np.array([[8, 8, 24, 24], [0, 0, 6, 40], [50, 10, 64, 30]], np.float32)
    scores = np.array([[0.9, 0.0], [0.0, 0.8], [0.0, 0.7]], np.float32)
    detector = Detector(save(fixed_detector(boxes, scores, _metadata()), detector_path.parent / "pad.onnx"))
    found = detector.detect(np.zeros((64, 64), np.uint8))
    assert [d.obj_id for d in found] == [1, 2]
    assert found[0].box == pytest.approx((0.0, 8 / 0.75, 16 / 0.75, 16 / 0.75))
    assert found[1].box == pytest.approx((42 / 0.75, 10 / 0.75, 64 - 42 / 0.75, 20 / 0.75))
    tall = detector.detect(np.zeros((96, 48), np.uint8))  # 1:2: scaled by 0.5 to 24 x 48, 20 columns of pad
    assert [d.box for d in tall] == [(0.0, 16.0, 8.0, 32.0)]


@pytest.mark.parametrize(("shape", "count"), [((1, 5000), 2), ((5000, 1), 0), ((3, 3), 2)])
def test_frames_of_extreme_aspect_are_letterboxed_without_error(tmp_path, shape, count):
    """A one-row frame keeps one row of the input, a one-column frame one column (where no box of this detector
    lies), a tiny frame is enlarged; every box is cut to the frame."""
    detector = Detector(save(fixed_detector(BOXES, SCORES, _metadata()), tmp_path / "det.onnx"))
    found = detector.detect(np.full(shape, 255, np.uint8))
    assert len(found) == count
    for d in found:
        x, y, w, h = d.box
        assert min(x, y) >= 0 and x + w <= shape[1] and y + h <= shape[0]


def test_detector_input_resizes_colour_and_depths_alike():
    colour = np.zeros((96, 128, 3), np.uint16)
    colour[..., 0] = 65535
    frame = detector_input(colour, WIDTH, HEIGHT)
    assert frame.shape == (HEIGHT, WIDTH) and frame.dtype == np.float32
    assert np.allclose(frame, 0.299, atol=1e-3)


def test_detector_input_is_the_same_for_8_bit_16_bit_and_float_frames():
    """One path from a frame to the detector's input: the 8-bit frame, its 16-bit copy and the float frame that
    ``read_image`` gives of it are the same pixels to the detector."""
    frame = np.random.default_rng(0).integers(0, 256, (300, 400), np.uint8)
    seen = detector_input(frame, WIDTH, HEIGHT)
    for same in (frame.astype(np.uint16) * 257, to_grey(frame), to_grey(frame).astype(np.float64)):
        assert np.array_equal(detector_input(same, WIDTH, HEIGHT), seen)


def test_detector_input_pads_a_frame_of_another_aspect_with_the_graphs_mean_grey():
    """An 8:3 frame in the 4:3 input: scaled to 64 x 24, 12 rows of the grey the graph normalises to 0 above and
    below."""
    seen = detector_input(np.full((48, 128), 255, np.uint8), WIDTH, HEIGHT)
    pad = np.full((12, WIDTH), DETECTOR_INPUT_MEAN, np.float32)
    assert seen.shape == (HEIGHT, WIDTH) and np.array_equal(seen[:12], pad) and np.array_equal(seen[36:], pad)
    assert np.array_equal(seen[12:36], np.ones((24, WIDTH), np.float32))


@pytest.mark.parametrize(("changes", "message"), [
    ({"score_threshold": 0.0}, "score threshold must be above 0"),
    ({"score_threshold": 1.5}, r"score threshold must lie in \[0, 1\]"),
    ({"nms_iou": float("nan")}, "NMS IoU must be finite"),
    ({"max_detections": 10**6}, r"max detections must lie in \[1, 1000\]"),
    ({"obj_ids": (1, 1)}, "lists an object id twice"),
    ({"input_width": 10}, r"input width must lie in \[32, 2048\]"),
])
def test_absurd_metadata_is_refused(changes, message):
    with pytest.raises(PopcodeError, match=message):
        _metadata(**changes)


@pytest.mark.parametrize(("option", "value", "message"), [
    ("score_threshold", -1.0, "score threshold"), ("nms_iou", 0.0, "NMS IoU must be above 0"),
    ("max_detections", 0, "max detections"),
])
def test_absurd_thresholds_from_a_caller_are_refused(detector_path, option, value, message):
    with pytest.raises(PopcodeError, match=message):
        Detector(detector_path, **{option: value})


def test_files_that_are_no_popcode_detector_are_named(tmp_path):
    bare = save(fixed_detector(BOXES, SCORES, None), tmp_path / "bare.onnx")
    with pytest.raises(PopcodeError, match=r"bare.onnx: not a popcode detector: its metadata has no"):
        Detector(bare)
    pose = save(linear_model(np.zeros(6, np.float32)), tmp_path / "pose.onnx")
    with pytest.raises(PopcodeError, match="not a popcode detector"):
        Detector(pose)
    graph = fixed_detector(BOXES, SCORES, _metadata())
    del graph.metadata_props[:]
    onnx.helper.set_model_props(graph, _metadata(input_width=96).to_props())
    wrong_size = save(graph, tmp_path / "size.onnx")
    with pytest.raises(PopcodeError, match=r"must be \[1, 1, 48, 96\] as its metadata says"):
        Detector(wrong_size)
    three = save(fixed_detector(BOXES, np.zeros((4, 3), np.float32), _metadata()), tmp_path / "three.onnx")
    with pytest.raises(PopcodeError, match="has 3 columns for the 2 object ids"):
        Detector(three)
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x07garbage")
    with pytest.raises(PopcodeError, match="corrupt.onnx"):
        Detector(corrupt)


def test_metadata_round_trips():
    metadata = _metadata(score_threshold=0.4, training={"epochs": 3})
    assert DetectorMetadata.from_props(metadata.to_props()) == metadata
    props = metadata.to_props()
    props["popcode_detector.format_version"] = "2"
    with pytest.raises(PopcodeError, match="detector format version 2 is not supported"):
        DetectorMetadata.from_props(props)


def test_predict_with_a_detector_from_the_command_line(tmp_path, capsys):
    """The frame alone: boxes of the detector's objects go to the model; a dark frame finds nothing (exit 0)."""
    import cv2

    from popcode_runtime.commands.cli import main

    detector = save(fixed_detector(BOXES, SCORES, _metadata(obj_ids=(3, 4)), brightness_gate=True),
                    tmp_path / "det.onnx")
    model = str(MODELS / "builtin-parts-3-6.onnx")
    bright, dark = tmp_path / "bright.png", tmp_path / "dark.png"
    cv2.imwrite(str(bright), np.full((HEIGHT, WIDTH), 255, np.uint8))
    cv2.imwrite(str(dark), np.zeros((HEIGHT, WIDTH), np.uint8))
    camera = ["--K", "60,60,31.5,23.5"]
    assert main(["predict", model, str(bright), "--detector", str(detector), *camera]) == 0
    out = capsys.readouterr().out.splitlines()
    assert [line.split(" box ")[0] for line in out if " box " in line] == [
        "object 3 detected (score 0.900) in", "object 4 detected (score 0.700) in"]
    assert main(["predict", model, str(dark), "--detector", str(detector), *camera]) == 0
    captured = capsys.readouterr()
    assert captured.out == "" and "no parts of objects [3, 4, 5, 6] found" in captured.err
    assert main(["predict", model, str(bright), "--detector", str(model), *camera]) == 2
    assert "it is a popcode pose model: give it as MODEL, not as --detector" in capsys.readouterr().err


def test_predict_takes_every_pose_model_and_counts_the_boxes_none_knows(tmp_path, capsys):
    """Boxes of objects 1 and 3: with the model of parts 3-6 alone, object 1's box is counted (text, JSON and
    ``FramePoseEstimator.last_skipped``); with the models of 1-2 and 3-6 both boxes get a pose. Several models
    are for --detector: boxes given by hand go to one model."""
    import json

    import cv2

    from popcode_runtime import FramePoseEstimator, read_image
    from popcode_runtime.commands.cli import main

    detector = str(save(fixed_detector(BOXES, SCORES, _metadata(obj_ids=(1, 3))), tmp_path / "det.onnx"))
    models = [str(MODELS / "builtin-parts-1-2.onnx"), str(MODELS / "builtin-parts-3-6.onnx")]
    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), np.full((HEIGHT, WIDTH), 255, np.uint8))
    frame = [str(image), "--detector", detector, "--K", "60,60,31.5,23.5"]
    assert main(["predict", models[1], *frame]) == 0
    out = capsys.readouterr().out
    assert out.count(" detected (score ") == 1 and "object 3 detected" in out
    assert "skipped 1 detection of objects no model knows: object 1 x1" in out
    assert main(["predict", models[1], *frame, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert len(printed["predictions"]) == 1 and printed["skipped_detections"] == {"1": 1}
    assert main(["predict", *models, *frame, "--json"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert [p["detection"]["obj_id"] for p in printed["predictions"]] == [1, 3]
    assert printed["skipped_detections"] == {} and printed["models"] == models
    assert main(["predict", *models, *frame]) == 0
    assert "skipped" not in capsys.readouterr().out
    alone = FramePoseEstimator.from_files(detector, models[1:])
    assert len(alone.estimate(read_image(image), K=[60, 60, 31.5, 23.5])) == 1 and alone.last_skipped == {1: 1}
    assert main(["predict", *models, str(image), "--box", "1,1,20,20"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "2 models with --box" in error


def test_a_detector_of_objects_no_pose_model_knows_is_refused(tmp_path, capsys):
    from popcode_runtime import FramePoseEstimator, PoseEstimator
    from popcode_runtime.commands.cli import main

    detector = save(fixed_detector(BOXES, SCORES, _metadata(obj_ids=(7, 8))), tmp_path / "det.onnx")
    model = MODELS / "builtin-parts-3-6.onnx"
    with pytest.raises(PopcodeError, match=r"the detector finds objects \[7, 8\] and the pose models know objects "
                                           r"\[3, 4, 5, 6\]: none in common"):
        FramePoseEstimator(Detector(detector), [PoseEstimator(model)])
    split = tmp_path / "split"
    (split / "000000" / "gray").mkdir(parents=True)
    assert main(["run", str(model), "--split", str(split), "--detector", str(detector), "--out",
                 str(tmp_path / "r.csv")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "none in common (wrong detector or wrong models?)" in error


def test_a_float_frame_resized_stays_in_range():
    """Area averaging of float pixels at 1.0 can round a hair past it; the detector's input stays in [0, 1]."""
    frame = np.random.default_rng(0).choice(np.float32([0.999999, 1.0]), size=(540, 720))
    resized = detector_input(frame, 256, 192)
    assert resized.shape == (192, 256) and resized.max() <= 1.0 and resized.min() >= 0.99


def test_the_cap_counts_boxes_after_suppression(tmp_path):
    """Three objects each seen at five overlapping places: a cap of three keeps one box of each, not the best
    three places (OpenCV's own top_k cuts the candidates before suppressing them)."""
    boxes = np.array([[x + d / 2, 8 + d / 2, x + 12 + d / 2, 20 + d / 2] for x in (2, 22, 42) for d in range(5)],
                     np.float32)
    scores = np.zeros((15, 1), np.float32)
    scores[:, 0] = [0.9 - 0.01 * d - 0.2 * (x // 20) for x in (2, 22, 42) for d in range(5)]
    detector = save(fixed_detector(boxes, scores, _metadata(obj_ids=(1,))), tmp_path / "det.onnx")
    found = Detector(detector, max_detections=3).detect(np.zeros((HEIGHT, WIDTH), np.uint8))
    assert [d.box[0] for d in found] == [2.0, 22.0, 42.0]
