"""A detector trained from a rendered scene split, resumed, exported, and run by the runtime alone: ``popcode
detect`` on an image and a split, ``popcode run --detector`` and ``popcode predict --detector``; refusals in
one line."""

from __future__ import annotations

import csv
import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from popcode_runtime.bop.detections import read_detections
from popcode_runtime.commands.cli import main as popcode
from popcode_runtime.geometry.crop import read_image_file
from popcode_runtime.inference.detector import Detector
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.inference.frame import FramePoseEstimator
from popcode_trainer.cli import main as trainer
from popcode_trainer.detection.frames import Frame, held_out
from popcode_trainer.detection.loop import fitted_epochs

MODELS = Path(__file__).resolve().parents[2] / "models"
POSE_MODEL = MODELS / "builtin-parts-3-6.onnx"
SMALL = ["--set", "detector.input_width=128", "--set", "detector.input_height=96", "--set",
         "detector.widths=[8, 8, 16, 16, 16]", "--set", "detector.fpn_channels=32", "--set", "detector.head_convs=1",
         "--set", "detector.batch_size=4", "--set", "detector.val_fraction=0.25"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Eight bin scenes of the built-in parts at 256 x 192."""
    out = tmp_path_factory.mktemp("detector") / "scenes"
    assert trainer(["render", "--objects", "builtin", "--out", str(out), "--scenes", "8", "--size", "256", "192",
                    "--seed", "4", "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def trained(scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two epochs of a small detector, then a third on resume."""
    run = tmp_path_factory.mktemp("detector") / "run"
    assert trainer(["train-detector", "--split", str(scenes), "--out", str(run), "--quiet", *SMALL,
                    "--set", "detector.epochs=2"]) == 0
    assert trainer(["train-detector", "--split", str(scenes), "--out", str(run), "--quiet", *SMALL,
                    "--set", "detector.epochs=3"]) == 0
    return run


def test_a_slow_first_epoch_is_corrected_by_the_second() -> None:
    """The budget's epochs come from the fastest epoch timed, counting the time already spent."""
    assert fitted_epochs(150.0, [15.0], 200) == 10
    assert fitted_epochs(150.0, [15.0, 2.0], 200) == 68  # 2 done, 133 s left at 2 s an epoch
    assert fitted_epochs(150.0, [2.0, 15.0], 200) == 68  # a slow second epoch does not shorten the run
    assert fitted_epochs(150.0, [15.0, 2.0], 40) == 40  # the config's epochs stay the most
    assert fitted_epochs(10.0, [15.0, 2.0], 200) == 2  # an overrun budget ends with the epochs done
    assert fitted_epochs(1.0, [15.0], 200) == 1


def test_a_validation_share_holds_out_at_least_one_image() -> None:
    """Four images at val_fraction 0.1 once held out none: every epoch's validation loss was NaN (issue 62)."""
    frames = [Frame(("split", 0, im_id), Path(f"{im_id}.png"), np.zeros((0, 4), np.float32), np.zeros(0, np.int64))
              for im_id in range(4)]
    assert [len(part) for part in held_out(frames, 0.1, seed=0)] == [3, 1]
    assert [len(part) for part in held_out(frames, 0.0, seed=0)] == [4, 0]


def test_training_resumes_and_exports_a_detector_the_runtime_reads(trained: Path) -> None:
    with (trained / "metrics.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [int(row["epoch"]) for row in rows] == [1, 2, 3]  # the resume ran the third epoch only
    assert all(np.isfinite(float(row["train_loss"])) and np.isfinite(float(row["val_loss"])) for row in rows)
    detector = Detector(trained / "detector.onnx")
    assert detector.obj_ids == (1, 2, 3, 4, 5, 6)
    meta = detector.metadata
    assert (meta.input_width, meta.input_height) == (128, 96)
    assert meta.training["epochs"] == 3 and meta.training["frames"] == {"train": 6, "val": 2,
                                                                         "splits": meta.training["frames"]["splits"]}


def test_a_resume_with_other_settings_is_refused(scenes: Path, trained: Path, capsys) -> None:
    assert trainer(["train-detector", "--split", str(scenes), "--out", str(trained), "--quiet", *SMALL,
                    "--set", "detector.lr=0.1"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "was trained with other settings (lr)" in error


@pytest.mark.parametrize(("option", "message"), [
    ("detector.widths=[8, 8]", "detector widths are 5 stage widths"),
    ("detector.input_width=100", "input_width must be a multiple of 32"),
    ("detector.score_threshold=0", "score threshold must be above 0"),
    ("detector.colour=1", "unknown detector setting(s) ['colour']"),
    ("train.lr=1", "train-detector settings are detector.KEY=VALUE"),
])
def test_bad_settings_are_refused_before_any_work(scenes: Path, tmp_path: Path, capsys, option: str,
                                                   message: str) -> None:
    assert trainer(["train-detector", "--split", str(scenes), "--out", str(tmp_path / "run"), "--set",
                    option]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_detect_writes_bop_default_detections_of_a_split(scenes: Path, trained: Path, tmp_path: Path) -> None:
    out = tmp_path / "detections.json"
    assert popcode(["detect", str(trained / "detector.onnx"), "--split", str(scenes), "--out", str(out),
                    "--score-threshold", "0.05", "--max-detections", "5", "--quiet"]) == 0
    detections = read_detections(out)  # the runtime's own reader accepts every entry
    assert detections and {d.obj_id for d in detections} <= {1, 2, 3, 4, 5, 6}
    per_image = {}
    for d in detections:
        per_image.setdefault(d.image_key, []).append(d)
    assert max(len(found) for found in per_image.values()) <= 5
    assert all(d.time_s > 0 for d in detections)


def test_predict_and_run_go_from_the_frame_alone(scenes: Path, trained: Path, tmp_path: Path, capsys) -> None:
    detector = str(trained / "detector.onnx")
    image = scenes / "000000" / "gray" / "000000.png"
    K = json.loads((scenes / "000000" / "scene_camera.json").read_text())["0"]["cam_K"]
    K_text = ",".join(str(v) for v in (K[0], K[4], K[2], K[5]))
    assert popcode(["predict", str(POSE_MODEL), str(image), "--detector", detector, "--score-threshold", "0.05",
                    "--max-detections", "3", "--K", K_text, "--json"]) == 0
    predictions = json.loads(capsys.readouterr().out)["predictions"]
    assert predictions and all(p["detection"]["obj_id"] in (3, 4, 5, 6) for p in predictions)
    out = tmp_path / "results.csv"
    assert popcode(["run", str(POSE_MODEL), "--split", str(scenes), "--detector", detector, "--score-threshold",
                    "0.05", "--max-detections", "3", "--out", str(out), "--quiet"]) == 0
    assert out.read_text().startswith("scene_id,im_id,obj_id,score,R,t,time")
    assert len(out.read_text().splitlines()) > 1


def test_frame_estimator_matches_detector_then_pose_model(scenes: Path, trained: Path) -> None:
    frame_estimator = FramePoseEstimator.from_files(trained / "detector.onnx", [POSE_MODEL], score_threshold=0.05,
                                                    max_detections=4)
    image = read_image_file(scenes / "000000" / "gray" / "000001.png")
    K = np.array(json.loads((scenes / "000000" / "scene_camera.json").read_text())["1"]["cam_K"]).reshape(3, 3)
    poses = frame_estimator.estimate(image, K)
    found = [d for d in frame_estimator.detector.detect(image) if d.obj_id in (3, 4, 5, 6)]
    assert [pose.detection for pose in poses] == found
    direct = PoseEstimator(POSE_MODEL).predict(image, [d.box for d in found], K=K, obj_ids=[d.obj_id for d in found],
                                               translation=True)
    for pose, expected in zip(poses, direct, strict=True):
        np.testing.assert_allclose(pose.prediction.R_m2c, expected.R_m2c, atol=1e-12)
        np.testing.assert_allclose(pose.prediction.t_m2c_mm, expected.t_m2c_mm, atol=1e-9)
    assert frame_estimator.last_skipped == dict(Counter(
        d.obj_id for d in frame_estimator.detector.detect(image) if d.obj_id in (1, 2)))


@pytest.mark.parametrize(("argv", "message"), [
    (["predict", "M", "I"], "give the objects' boxes (--box X,Y,W,H, repeatable) or a detector"),
    (["predict", "M", "I", "--box", "1,1,5,5", "--score-threshold", "0.5"], "set how --detector runs"),
    (["detect", "D"], "give an IMAGE to detect in, or a --split"),
    (["detect", "D", "--split", "S"], "add --out JSON"),
    (["detect", "D", "I", "--out", "x.json"], "--out writes the detections of a --split"),
    (["run", "M", "--split", "S", "--gt-boxes", "--nms-iou", "0.5"], "--nms-iou sets how --detector runs"),
])
def test_option_mistakes_cost_one_line(argv: list[str], message: str, capsys) -> None:
    assert popcode(argv) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and message in error


def test_boxes_of_objects_no_model_knows_are_skipped_and_a_pose_model_is_no_detector(
        scenes: Path, trained: Path, capsys) -> None:
    other = MODELS / "builtin-parts-1-2.onnx"
    frame_estimator = FramePoseEstimator.from_files(trained / "detector.onnx", [other])
    assert frame_estimator.unknown_objects == [3, 4, 5, 6]
    assert popcode(["detect", str(other), str(scenes / "000000" / "gray" / "000000.png")]) == 2
    assert "not a popcode detector" in capsys.readouterr().err
