"""The models shipped in ``models/``: they load, cover every built-in part once, and estimate the sample
images' rotations about as well as their model card says."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from popcode_runtime import Detector, FramePoseEstimator, PoseEstimator, read_image
from popcode_runtime.geometry.rotations import geodesic_angle
from popcode_runtime.geometry.symmetries import symmetry_transforms

MODELS = Path(__file__).resolve().parents[2] / "models"
SAMPLES = MODELS / "samples" / "samples.json"
DETECTOR = MODELS / "builtin-parts-detector.onnx"
# The card reports the test-split MSSD recall; on the six samples we only ask that most poses are
# roughly right up to symmetry (a wrong model, a broken crop or decoder gives errors near 90 deg or more).
ROUGHLY_RIGHT_DEG = 30.0
# The sample bin frame's ten parts are 89-100 % visible; the detector's card reports a recall of about 80 % of
# the instances at least 30 % visible on the bin splits (IoU 0.5, object right): at least eight of ten here.
FOUND_IN_SAMPLE_BIN = 8


def shipped_models() -> dict[int, Path]:
    """Object id -> the shipped model that estimates it."""
    owners: dict[int, Path] = {}
    for path in sorted(set(MODELS.glob("*.onnx")) - {DETECTOR}):
        for obj_id in PoseEstimator(path).metadata.objects:
            assert obj_id not in owners, f"object {obj_id} is in {owners.get(obj_id)} and {path}"
            owners[obj_id] = path
    return owners


def samples() -> list[dict]:
    return json.loads(SAMPLES.read_text())["samples"]


def error_up_to_symmetry_deg(R_est: np.ndarray, R_true: np.ndarray, info: dict) -> float:
    candidates = R_true @ symmetry_transforms(info).R
    return float(np.degrees(geodesic_angle(candidates, R_est).min()))


def test_every_builtin_part_has_one_small_model() -> None:
    owners = shipped_models()
    assert sorted(owners) == [1, 2, 3, 4, 5, 6]
    for path in set(owners.values()):
        assert path.stat().st_size < 8e6, f"{path.name} is {path.stat().st_size / 1e6:.1f} MB"
        assert (MODELS / "README.md").read_text().count(path.name) >= 1


@pytest.mark.parametrize("decoder", ["argmax", "refined"])
def test_samples_are_estimated_up_to_symmetry(decoder: str) -> None:
    owners = shipped_models()
    errors, distance_errors = [], []
    for sample in samples():
        estimator = PoseEstimator(owners[sample["obj_id"]], decoder=decoder)
        image = read_image(SAMPLES.parent / sample["image"])
        prediction = estimator.predict(image, [sample["box"]], K=sample["K"], obj_ids=[sample["obj_id"]],
                                       translation=True)[0]
        info = estimator.metadata.objects[sample["obj_id"]]
        errors.append(error_up_to_symmetry_deg(prediction.R_m2c, np.array(sample["R_m2c"]), info))
        t_true = np.array(sample["t_m2c_mm"])
        distance_errors.append(np.linalg.norm(prediction.t_m2c_mm - t_true) / np.linalg.norm(t_true))
    assert np.median(errors) < ROUGHLY_RIGHT_DEG, errors
    # With the true rotation the box fit is within 1 % (bench/translation.py); a rotation tens of degrees
    # off changes the silhouette, so the translation is asked to be within 10 % of the distance.
    assert np.median(distance_errors) < 0.1, distance_errors


def test_shipped_models_carry_a_calibrated_confidence() -> None:
    """Every shipped model reports P(error < its threshold) from its calibrator, a probability per sample."""
    owners = shipped_models()
    for path in set(owners.values()):
        calibrator = PoseEstimator(path).metadata.confidence
        assert calibrator is not None and calibrator.threshold_deg == 10.0, path.name
        assert calibrator.fitted_on["held_out_instances"] >= 100, path.name
    confidences = []
    for sample in samples():
        estimator = PoseEstimator(owners[sample["obj_id"]])
        image = read_image(SAMPLES.parent / sample["image"])
        prediction = estimator.predict(image, [sample["box"]], K=sample["K"], obj_ids=[sample["obj_id"]])[0]
        confidences.append(prediction.confidence)
    assert all(0.0 <= c <= 1.0 for c in confidences) and len(set(confidences)) == len(confidences)


def _iou(a: list[float], b: tuple[float, ...]) -> float:
    width = max(0.0, min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0]))
    height = max(0.0, min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1]))
    return width * height / (a[2] * a[3] + b[2] * b[3] - width * height)


def test_the_shipped_detector_finds_the_sample_bins_parts_and_their_poses() -> None:
    """The detector of the six parts on the sample bin frame (ten parts), then the shipped pose models in its
    boxes: most parts found with their object, most found poses roughly right up to symmetry."""
    detector = Detector(DETECTOR)
    assert detector.obj_ids == (1, 2, 3, 4, 5, 6)
    assert DETECTOR.stat().st_size < 8e6 and (MODELS / "README.md").read_text().count(DETECTOR.name) >= 1
    sample = json.loads(SAMPLES.read_text())["bin"]
    image = read_image(SAMPLES.parent / sample["image"])
    frames = FramePoseEstimator(detector, [PoseEstimator(path) for path in sorted(set(shipped_models().values()))])
    poses = frames.estimate(image, K=sample["K"])
    infos = {obj_id: info for model in frames.estimators for obj_id, info in model.metadata.objects.items()}
    found, errors = 0, []
    for instance in sample["instances"]:
        hits = [pose for pose in poses if pose.detection.obj_id == instance["obj_id"]
                and _iou(instance["bbox_obj"], pose.detection.box) >= 0.5]
        if hits:
            found += 1
            errors.append(error_up_to_symmetry_deg(hits[0].prediction.R_m2c, np.array(instance["R_m2c"]),
                                                   infos[instance["obj_id"]]))
    assert found >= FOUND_IN_SAMPLE_BIN, (found, [p.detection for p in poses])
    assert np.median(errors) < ROUGHLY_RIGHT_DEG, errors
