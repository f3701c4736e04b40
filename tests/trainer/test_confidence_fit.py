"""Fitting the confidence calibrator at export, and judging a confidence (calibration and usefulness)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from popcode_runtime import PoseEstimator, read_image
from popcode_runtime.coding.confidence import FEATURES
from popcode_trainer.cli import main
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.render import render_builtin_split
from popcode_trainer.export.confidence_fit import fit_logistic
from popcode_trainer.metrics.confidence import (
    auroc,
    evaluate_confidence,
    expected_calibration_error,
    most_confident,
    rotation_errors_deg,
)

OBJ_ID = 1  # the flanged sleeve: continuous symmetry, an axis-only code that a tiny model learns in seconds


def test_fit_keeps_weights_non_negative_and_finds_the_informative_feature() -> None:
    rng = np.random.default_rng(0)
    features = rng.normal(size=(4000, len(FEATURES)))

    def outcomes(logits: np.ndarray) -> np.ndarray:
        return rng.random(len(logits)) < 1.0 / (1.0 + np.exp(-logits))

    weights, bias = fit_logistic(features, outcomes(0.5 + 2.0 * features[:, 0]))  # feature 0 informs, 1 and 2 not
    assert weights[0] == pytest.approx(2.0, rel=0.15) and bias == pytest.approx(0.5, abs=0.2)
    assert (weights[1:] >= 0).all() and (weights[1:] < 0.15).all()
    weights, _ = fit_logistic(features, outcomes(0.5 - 1.5 * features[:, 2]))  # feature 2 high: more often wrong
    assert weights[2] == 0.0 and (weights < 0.15).all()  # clamped, never used backwards


def test_ece_auroc_and_coverage_on_known_cases() -> None:
    rng = np.random.default_rng(1)
    p = rng.random(20000)
    calibrated = rng.random(len(p)) < p
    ece, bins = expected_calibration_error(p, calibrated)
    assert ece < 0.02 and sum(b["count"] for b in bins) == len(p)
    overconfident, _ = expected_calibration_error(np.full(len(p), 0.95), calibrated)
    assert overconfident == pytest.approx(0.95 - calibrated.mean(), abs=1e-9)
    correct = np.array([False, False, True, True])
    assert auroc(np.array([0.1, 0.2, 0.8, 0.9]), correct) == 1.0
    assert auroc(np.array([0.9, 0.8, 0.2, 0.1]), correct) == 0.0
    assert auroc(np.full(4, 0.5), correct) == 0.5  # ties count half
    assert np.isnan(auroc(np.array([0.1, 0.2]), np.array([True, True])))
    np.testing.assert_array_equal(most_confident(np.array([0.3, 0.9, 0.1, 0.5]), 0.5), [False, True, False, True])


@pytest.mark.slow
def test_export_fits_a_calibrator_whose_confident_estimates_are_the_better_ones(tmp_path: Path,
                                                                               capsys: pytest.CaptureFixture) -> None:
    """A tiny model trained on a rendered split: on images it never saw, its more confident half is more often
    right, and evaluate reports the confidence's calibration and usefulness."""
    split = render_builtin_split(tmp_path / "split", images_per_object=200, obj_ids=[OBJ_ID])
    config = tmp_path / "tiny.toml"
    config.write_text(f"""
[data]
splits = ["{split}"]
models_dir = "{split / 'models'}"
obj_ids = [{OBJ_ID}]
val_fraction = 0.5
num_workers = 0
[code]
n_axes = 162
n_angles = 12
[network]
trunk = "residual"
conv_channels = [8, 16, 16]
squeeze_channels = 4
hidden = [64, 32, 32]
[train]
loss = "mse+cross_entropy"
epochs = 30
batch_size = 16
lr = 3e-3
out_dir = "{tmp_path / 'run'}"
""")
    assert main(["train", "--config", str(config)]) == 0
    model = tmp_path / "model.onnx"
    assert main(["export", str(tmp_path / "run" / "last.pt"), "--out", str(model),
                 "--confidence-threshold", "30"]) == 0
    assert "confidence calibrator: fitted on 100 held-out crops" in capsys.readouterr().out
    estimator = PoseEstimator(model)
    calibrator = estimator.metadata.confidence
    assert calibrator is not None and calibrator.threshold_deg == 30.0
    assert calibrator.refined is not None  # a second fit for the refined decoder, on the same held-out codes

    test = render_builtin_split(tmp_path / "test", images_per_object=64, obj_ids=[OBJ_ID], seed=7)
    instances = read_bop_split(test, test / "models").instances
    predictions = [estimator.predict(read_image(inst.image_path), [inst.box], K=inst.K)[0] for inst in instances]
    confidence = np.array([p.confidence for p in predictions])
    errors = rotation_errors_deg(np.stack([p.R_m2c for p in predictions]), np.stack([i.R_m2c for i in instances]),
                                 np.full(len(instances), OBJ_ID), estimator.metadata.objects)
    assert ((confidence >= 0) & (confidence <= 1)).all()
    confident = most_confident(confidence, 0.5)
    assert np.median(errors[confident]) < np.median(errors[~confident])
    assert auroc(confidence, errors < 30.0) > 0.6

    evaluation = evaluate_confidence(confidence, True, errors, 30.0, lambda mask: float(mask.mean()))
    assert evaluation.kind == "calibrated confidence" and 0.0 <= evaluation.ece <= 1.0
    assert evaluation.mssd_at_coverage[0.5] == pytest.approx(0.5, abs=1 / len(instances))

    assert main(["evaluate", str(model), "--split", str(test), "--models-dir", str(test / "models"),
                 "--out", str(tmp_path / "eval"), "--no-vsd"]) == 0
    report = json.loads((tmp_path / "eval" / "report.json").read_text())["methods"]["model"]["confidence"]
    assert report["kind"] == "calibrated confidence" and report["threshold_deg"] == 30.0
    assert report["auroc"] == pytest.approx(evaluation.auroc)  # the same estimates as the runtime's, one by one
    assert (tmp_path / "eval" / "reliability.png").read_bytes()[:4] == b"\x89PNG"
    assert "## Confidence" in (tmp_path / "eval" / "report.md").read_text()
