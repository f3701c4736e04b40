"""The engine seam: any callable crops -> outputs runs the same pipeline as the ONNX model of the same weights."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest
from onnx import numpy_helper
from onnx_models import linear_model, save
from symmetry_cases import CASES

from popcode_runtime import CodeLayout, ModelMetadata, PopcodeError, PoseEstimator, Representation, RotationFrame
from popcode_runtime.model.engine import OnnxEngine, onnx_session

LAYOUT = CodeLayout(n_axes=162, n_angles=36)
K = [1075.65, 1073.90, 360.0, 270.0]
BOXES = [[100.0, 120.0, 90.0, 80.0], [400.0, 300.0, 150.0, 120.0], [600.0, 420.0, 100.0, 100.0]]
METADATA = ModelMetadata(representation=Representation.POPULATION_CODE, code=LAYOUT,
                         objects={5: CASES["two_fold"]}, rotation_frame=RotationFrame.ALLOCENTRIC)


class NumpyEngine:
    """The graph of :func:`onnx_models.linear_model` in numpy: 32x32 average pool, flatten, ``@ W + B``."""

    def __init__(self, weight: np.ndarray, bias: np.ndarray) -> None:
        self.weight, self.bias = weight, bias

    def __call__(self, crops: np.ndarray) -> np.ndarray:
        n, _, size, _ = crops.shape
        pooled = crops.reshape(n, size // 32, 32, size // 32, 32).mean(axis=(2, 4)).reshape(n, -1)
        return (pooled @ self.weight + self.bias).astype(np.float32)


@pytest.fixture
def onnx_file(tmp_path: Path) -> Path:
    bias = np.random.default_rng(3).uniform(0.0, 0.2, LAYOUT.size).astype(np.float32)
    return save(linear_model(bias, weight_scale=2.0, metadata=METADATA), tmp_path / "linear.onnx")


@pytest.fixture
def scene() -> np.ndarray:
    return np.random.default_rng(1).integers(0, 256, size=(540, 720), dtype=np.uint8)


def numpy_twin(path: Path, decoder: str = "argmax") -> PoseEstimator:
    """The same weights as the ONNX file, run by numpy, with the file's metadata."""
    weights = {init.name: numpy_helper.to_array(init) for init in onnx.load(str(path)).graph.initializer}
    return PoseEstimator.from_engine(NumpyEngine(weights["W"], weights["B"]), OnnxEngine(path).metadata, decoder)


@pytest.mark.parametrize("decoder", ["argmax", "refined"])
def test_a_numpy_engine_predicts_what_the_onnx_model_predicts(onnx_file: Path, scene: np.ndarray,
                                                             decoder: str) -> None:
    from_file, from_engine = PoseEstimator(onnx_file, decoder=decoder), numpy_twin(onnx_file, decoder)
    options = {"K": K, "return_code": True, "top_k": 3, "translation": True}
    for a, b in zip(from_file.predict(scene, BOXES, **options), from_engine.predict(scene, BOXES, **options),
                    strict=True):
        np.testing.assert_allclose(b.code, a.code, atol=1e-4)  # float32 sums in another order
        np.testing.assert_allclose(b.R_m2c, a.R_m2c, atol=1e-4)
        np.testing.assert_allclose(b.t_m2c_mm, a.t_m2c_mm, rtol=1e-4)
        assert b.score == pytest.approx(a.score, abs=1e-4) and b.obj_id == a.obj_id == 5
        assert len(b.hypotheses) == len(a.hypotheses) > 1
        for h_b, h_a in zip(b.hypotheses, a.hypotheses, strict=True):
            np.testing.assert_allclose(h_b.R_m2c, h_a.R_m2c, atol=1e-4)
    assert from_file.providers == ["CPUExecutionProvider"] and from_engine.providers == []


@pytest.mark.parametrize(("output", "message"), [
    (np.zeros((3, LAYOUT.size), np.float64), "float64"),
    (np.zeros((3, LAYOUT.size - 1), np.float32), r"\(3, 5831\)"),
    (np.zeros((2, LAYOUT.size), np.float32), r"float32 \(3, 5832\)"),
    ([[0.0] * LAYOUT.size] * 3, "list"),
])
def test_an_engine_output_of_the_wrong_shape_or_type_is_refused(scene: np.ndarray, output: object,
                                                                message: str) -> None:
    estimator = PoseEstimator.from_engine(lambda crops: output, METADATA)
    with pytest.raises(PopcodeError, match=message):
        estimator.predict(scene, BOXES, K=K)


def test_from_engine_checks_its_decoder() -> None:
    with pytest.raises(PopcodeError, match="unknown decoder"):
        PoseEstimator.from_engine(lambda crops: crops, METADATA, decoder="median")


def test_sessions_from_bytes_and_their_errors(onnx_file: Path) -> None:
    session = onnx_session(onnx_file.read_bytes(), threads=1)
    assert session.get_providers() == ["CPUExecutionProvider"]
    with pytest.raises(PopcodeError, match="cannot load the given model bytes"):
        onnx_session(b"not a model")
    with pytest.raises(PopcodeError, match="threads must be >= 0"):
        onnx_session(onnx_file, threads=-1)
