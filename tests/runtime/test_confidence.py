"""The runtime's calibrated confidence: code features, the calibrator, and how a model carries it."""

from __future__ import annotations

import json

import numpy as np
import pytest
from onnx_models import linear_model, save
from symmetry_cases import CASES

from popcode_runtime import CodeLayout, ModelMetadata, PopcodeError, PopulationCode, PoseEstimator, Representation
from popcode_runtime.coding.confidence import FEATURES, Calibrator, code_features, default_rival_radius_deg
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, random_rotations
from popcode_runtime.geometry.symmetries import symmetry_rotations

LAYOUT = CodeLayout(n_axes=162, n_angles=18)
RADIUS_DEG = default_rival_radius_deg(LAYOUT)
PEAK, MARGIN, CONCENTRATION = range(len(FEATURES))


def _code(R: np.ndarray, case: str = "none") -> np.ndarray:
    return PopulationCode(LAYOUT).encode(R[None], symmetry_rotations(CASES[case]))[0].astype(np.float32)


def _calibrator(weights=(1.0, 2.0, 3.0), bias=-3.0) -> Calibrator:
    return Calibrator(threshold_deg=10.0, rival_radius_deg=RADIUS_DEG, weights=weights, bias=bias)


@pytest.mark.parametrize("case", ["none", "two_fold", "four_fold"])
def test_an_exact_code_has_no_rival_however_many_symmetric_peaks(case: str) -> None:
    """Symmetric equivalents are the same pose: an exact code puts all its mass on the winning pose."""
    R = random_rotations(5, np.random.default_rng(3))
    codes = np.stack([_code(r, case) for r in R])
    features = code_features(LAYOUT, codes, symmetry_rotations(CASES[case]), RADIUS_DEG)
    np.testing.assert_allclose(features[:, PEAK], codes.max(axis=1))
    # a 4-fold part's four peaks each hold a quarter of the mass: counted as rivals, the share would be ~0.25;
    # what is missing from 1 is the Gaussians' tails beyond the radius around the (off-grid) winning neuron
    assert (features[:, CONCENTRATION] > 0.85).all()
    assert (features[:, MARGIN] > 0.7 * features[:, PEAK]).all()


def test_a_second_pose_is_a_rival_and_lowers_margin_and_concentration() -> None:
    R = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), 0.3)
    rival = axis_angle_to_matrix(np.array([1.0, 0.0, 0.0]), 2.0) @ R  # 115 deg away: another pose, not a symmetry
    alone, contested = _code(R), _code(R) + 0.8 * _code(rival)
    features = code_features(LAYOUT, np.stack([alone, contested]), np.eye(3)[None], RADIUS_DEG)
    assert features[1, MARGIN] < 0.3 * features[0, MARGIN]
    assert features[1, CONCENTRATION] < 0.7 < features[0, CONCENTRATION]


def test_calibrator_is_monotone_bounded_and_refuses_negative_weights() -> None:
    calibrator = _calibrator()
    features = np.random.default_rng(0).normal(scale=50.0, size=(1000, len(FEATURES)))
    p = calibrator.probability(features)
    assert ((p >= 0) & (p <= 1)).all() and np.isfinite(p).all()
    for column in range(len(FEATURES)):  # raising any feature never lowers the confidence
        higher = features.copy()
        higher[:, column] += 1.0
        assert (calibrator.probability(higher) >= p).all()
    with pytest.raises(PopcodeError, match="weight of margin"):
        _calibrator(weights=(1.0, -0.5, 1.0))
    with pytest.raises(PopcodeError, match="3 numbers"):
        _calibrator(weights=(1.0, 1.0))


@pytest.mark.parametrize("entry, message", [
    ({"features": ["peak"]}, "uses features"),
    ({"bias": "high"}, "bias"),
    ({"threshold_deg": 0.0}, "must be positive"),
    ({"threshold_deg": float("nan")}, "NaN"),
    ({"weights": None}, "weights"),
    ({"refined": {"weights": [1.0, 1.0, 1.0]}}, "refined needs weights and bias"),
    ({"refined": {"weights": [1.0, -1.0, 1.0], "bias": 0.0}}, "refined weight of margin"),
    ({"weights": [1e308, 1.0, 1.0]}, r"weight of peak must lie in \[0, 1000\]"),  # every confidence 0 or 1
    ({"bias": -1e300}, r"confidence bias must lie in \[-1000, 1000\]"),
    ({"refined": {"weights": [1.0, 1.0, 1.0], "bias": 5e3}}, "refined bias must lie in"),
])
def test_a_broken_calibrator_in_the_metadata_is_refused_at_load(tmp_path, entry: dict, message: str) -> None:
    meta = ModelMetadata(Representation.POPULATION_CODE, LAYOUT, {1: CASES["none"]}, confidence=_calibrator())
    props = meta.to_props()
    props["popcode.confidence"] = json.dumps({**json.loads(props["popcode.confidence"]), **entry})
    with pytest.raises(PopcodeError, match=message):
        ModelMetadata.from_props(props)


def test_a_single_variable_model_cannot_carry_a_calibrator() -> None:
    with pytest.raises(PopcodeError, match="cannot carry one"):
        ModelMetadata(Representation.SINGLE_VARIABLE, LAYOUT, {1: CASES["none"]}, confidence=_calibrator())


def test_the_model_reports_its_calibrated_confidence_and_none_without_a_calibrator(tmp_path) -> None:
    R = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), 1.0)
    code = _code(R, "two_fold")
    image, box = np.full((200, 200), 0.5, np.float32), [50.0, 50.0, 80.0, 80.0]
    plain = ModelMetadata(Representation.POPULATION_CODE, LAYOUT, {1: CASES["two_fold"]})
    calibrated = ModelMetadata(Representation.POPULATION_CODE, LAYOUT, {1: CASES["two_fold"]},
                               confidence=_calibrator())
    without = PoseEstimator(save(linear_model(code, metadata=plain), tmp_path / "plain.onnx"))
    with_calibrator = PoseEstimator(save(linear_model(code, metadata=calibrated), tmp_path / "calibrated.onnx"))
    assert without.predict(image, [box])[0].confidence is None
    assert without.predict(image, [box])[0].to_dict()["confidence"] is None
    prediction = with_calibrator.predict(image, [box], return_code=True)[0]
    features = code_features(LAYOUT, prediction.code[None], symmetry_rotations(CASES["two_fold"]), RADIUS_DEG)
    assert prediction.confidence == pytest.approx(float(_calibrator().probability(features)[0]))
    assert with_calibrator.metadata.confidence == _calibrator()  # survives the ONNX metadata round trip


def test_the_refined_decoder_has_its_own_fit_and_falls_back_to_argmax_without_one(tmp_path) -> None:
    features = np.array([[0.9, 0.5, 0.8], [0.2, 0.05, 0.3]])
    both = Calibrator(10.0, RADIUS_DEG, (1.0, 2.0, 3.0), -3.0, refined=((0.5, 0.0, 4.0), -1.0))
    np.testing.assert_allclose(both.probability(features, "refined"),
                               Calibrator(10.0, RADIUS_DEG, (0.5, 0.0, 4.0), -1.0).probability(features))
    np.testing.assert_allclose(both.probability(features, "argmax"), _calibrator().probability(features))
    np.testing.assert_allclose(_calibrator().probability(features, "refined"), _calibrator().probability(features))
    meta = ModelMetadata(Representation.POPULATION_CODE, LAYOUT, {1: CASES["none"]}, confidence=both)
    assert ModelMetadata.from_props(meta.to_props()).confidence == both  # survives the metadata round trip
    code = _code(axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), 1.0))
    model = save(linear_model(code, metadata=meta), tmp_path / "m.onnx")
    image, box = np.full((200, 200), 0.5, np.float32), [50.0, 50.0, 80.0, 80.0]
    by_decoder = {d: PoseEstimator(model, decoder=d).predict(image, [box], return_code=True)[0] for d in
                  ("argmax", "refined")}
    features = code_features(LAYOUT, by_decoder["refined"].code[None], np.eye(3)[None], RADIUS_DEG)
    assert by_decoder["refined"].confidence == pytest.approx(float(both.probability(features, "refined")[0]))
    assert by_decoder["argmax"].confidence == pytest.approx(float(both.probability(features, "argmax")[0]))
