"""Values outside the BOP format's domain are refused in one line naming file and field, never coerced (issue 30).

One bounded JSON reader (:func:`popcode_runtime.base.files.read_json`) and one reading of ids
(:mod:`popcode_runtime.bop.split`) serve every reader, so these cases hold for ``popcode run``, evaluation and
training alike.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from popcode_runtime.base.checks import number
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import read_json
from popcode_runtime.bop.detections import ground_truth_boxes, read_detections
from popcode_runtime.bop.split import split_images
from popcode_runtime.coding.confidence import FEATURES, Calibrator
from popcode_runtime.commands.cli import main
from popcode_runtime.geometry.camera import parse_camera_matrix
from popcode_runtime.geometry.translation import object_points_mm

MODELS = Path(__file__).resolve().parents[2] / "models"

GT = {"cam_R_m2c": [1, 0, 0, 0, 1, 0, 0, 0, 1], "cam_t_m2c": [0, 0, 300], "obj_id": 3}
INFO = {"bbox_obj": [10, 10, 30, 30], "bbox_visib": [10, 10, 30, 30], "visib_fract": 1.0}
CAMERA = {"cam_K": [100, 0, 32, 0, 100, 32, 0, 0, 1], "depth_scale": 1.0}


def _split(root: Path, gt: object = None, keys: tuple[str, ...] = ("0",), scene: str = "000001",
           images: tuple[str, ...] = ("000000.png",)) -> Path:
    """One scene of 64 x 64 grey images with the given scene_gt entries and keys."""
    folder = root / scene
    (folder / "gray").mkdir(parents=True)
    for name in images:
        cv2.imwrite(str(folder / "gray" / name), np.full((64, 64), 90, np.uint8))
    entry = [GT] if gt is None else gt
    (folder / "scene_gt.json").write_text(json.dumps({key: entry for key in keys}))
    (folder / "scene_gt_info.json").write_text(json.dumps({key: [INFO] * len(entry) for key in keys}))
    (folder / "scene_camera.json").write_text(json.dumps({key: CAMERA for key in keys}))
    return root


@pytest.mark.parametrize(("text", "message"), [
    ("[" * 100_000 + "]" * 100_000, "nests JSON too deeply"),
    ('{"0": [{"obj_id": ' + "7" * 400 + "}]}", "an integer of 400 digits"),
    ('{"0": ' + "1" * 4300 + "}", "an integer of 4300 digits"),
    ('{"0": [1e400]}', "overflows a float"),
    ('{"0": [NaN]}', "NaN is not a JSON number"),
    ('{"0": [-Infinity]}', "-Infinity is not a JSON number"),
])
def test_json_outside_the_formats_numbers_is_refused(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "scene_gt.json"
    path.write_text(text)
    with pytest.raises(PopcodeError, match=message) as caught:
        read_json(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize(("obj_id", "shown"), [(1.7, "1.7"), ("1", "'1'"), ([1], r"\[1\]"), (True, "True"),
                                               (-2, "-2"), (None, "None")])
def test_object_ids_are_not_coerced(tmp_path: Path, obj_id: object, shown: str) -> None:
    split = _split(tmp_path, gt=[{**GT, "obj_id": obj_id}])
    message = rf"'obj_id' in image 0, object 0 must be a non-negative integer, got {shown}"
    with pytest.raises(PopcodeError, match=message):
        ground_truth_boxes(split)


@pytest.mark.parametrize(("key", "message"), [
    ("\u0667", "keys must be integer ids"),  # an Arabic-Indic seven: int() would read it as 7
    ("1_0", "keys must be integer ids"),
    (" 1", "keys must be integer ids"),
    ("+1", "keys must be integer ids"),
])
def test_keys_are_ascii_digits(tmp_path: Path, key: str, message: str) -> None:
    split = _split(tmp_path, keys=(key,))
    with pytest.raises(PopcodeError, match=message):
        ground_truth_boxes(split)


def test_two_keys_of_one_id_are_refused(tmp_path: Path) -> None:
    split = _split(tmp_path, keys=("1", "01"))
    with pytest.raises(PopcodeError, match="'1' and '01' both stand for id 1"):
        ground_truth_boxes(split)


def test_two_folders_of_one_scene_are_refused(tmp_path: Path) -> None:
    _split(tmp_path, scene="000001")
    _split(tmp_path, scene="1")
    with pytest.raises(PopcodeError, match="both stand for id 1"):
        split_images(tmp_path)


def test_folders_named_in_other_digits_are_not_scenes(tmp_path: Path) -> None:
    _split(tmp_path, scene="000001")
    _split(tmp_path, scene="\u0662")  # an Arabic-Indic two
    assert sorted(split_images(tmp_path)) == [(1, 0)]


def test_two_files_of_one_image_are_refused(tmp_path: Path) -> None:
    split = _split(tmp_path, images=("000000.png", "000000.jpg"))
    with pytest.raises(PopcodeError, match="are two files of one image"):
        split_images(split)


@pytest.mark.parametrize("score", [-3, 5, 1.0001])
def test_detection_scores_are_confidences(tmp_path: Path, score: float) -> None:
    path = tmp_path / "detections.json"
    path.write_text(json.dumps([{"scene_id": 1, "image_id": 0, "category_id": 3, "bbox": [1, 1, 9, 9],
                                 "score": score, "time": 0.1}]))
    with pytest.raises(PopcodeError, match=r"detection 0: 'score' must lie in \[0, 1\]"):
        read_detections(path)


def test_run_names_a_bad_split_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    split = _split(tmp_path / "split", gt=[{**GT, "obj_id": "3"}])
    out = tmp_path / "results.csv"
    code = main(["run", str(MODELS / "builtin-parts-3-6.onnx"), "--split", str(split), "--gt-boxes",
                 "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "'obj_id' in image 0, object 0 must be a non-negative integer" in err
    assert err.count("\n") == 1 and not out.exists()


@pytest.mark.parametrize("value", [10**400, 10**6000, -(10**400)], ids=["400-digits", "6000-digits", "minus-400"])
def test_integers_beyond_a_float_are_one_line_in_every_reader(value: int) -> None:
    """JSON files are bounded by their reader; the Python API takes any int, so the checks must too."""
    weights = [0.0] * len(FEATURES)
    calls = [lambda: number(value, "diameter"), lambda: Calibrator(5.0, 10.0, weights, value),
             lambda: object_points_mm({"hull_points_mm": [[value, 0, 0]] * 4}),
             lambda: parse_camera_matrix([value, 500, 80, 60])]
    for call in calls:
        with pytest.raises(PopcodeError):
            call()
