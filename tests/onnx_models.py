"""Small real ONNX models with popcode metadata, built with the onnx package for tests.

The graph is average-pool -> flatten -> MatMul + bias, so its output is a known
code (the bias) plus a small input-dependent part: enough to test cropping,
batching, metadata checks and decoding through real onnxruntime inference.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from popcode_runtime.model.detector_metadata import (
    DETECTOR_BOXES,
    DETECTOR_INPUT,
    DETECTOR_SCORES,
    DetectorMetadata,
)
from popcode_runtime.model.metadata import INPUT_NAME, OUTPUT_NAME, ModelMetadata

ONNX_IR_VERSION = 10  # onnx >= 1.23 writes IR 14, which current onnxruntime releases refuse
ONNX_OPSET = 17


def linear_model(
    bias: np.ndarray,
    weight_scale: float = 0.0,
    metadata: ModelMetadata | None = None,
    output_dim: int | None = None,
    input_size: int = 128,
    seed: int = 0,
) -> onnx.ModelProto:
    """``code = flatten(avgpool32(image)) @ W + bias`` with W ~ weight_scale * N(0, 1)."""
    dim = len(bias) if output_dim is None else output_dim
    pooled = (input_size // 32) ** 2
    weight = (np.random.default_rng(seed).normal(size=(pooled, dim)) * weight_scale).astype(np.float32)
    nodes = [
        helper.make_node("AveragePool", [INPUT_NAME], ["pooled"], kernel_shape=[32, 32], strides=[32, 32]),
        helper.make_node("Flatten", ["pooled"], ["flat"], axis=1),
        helper.make_node("MatMul", ["flat", "W"], ["mm"]),
        helper.make_node("Add", ["mm", "B"], [OUTPUT_NAME]),
    ]
    graph = helper.make_graph(
        nodes,
        "popcode_test",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["N", 1, input_size, input_size])],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, ["N", dim])],
        initializer=[numpy_helper.from_array(weight, "W"),
                     numpy_helper.from_array(np.asarray(bias, np.float32)[:dim], "B")],
    )
    return _checked_model(graph, metadata)


def _checked_model(graph: onnx.GraphProto, metadata: ModelMetadata | DetectorMetadata | None) -> onnx.ModelProto:
    """The graph as a model onnxruntime reads, with the metadata's props, checked."""
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", ONNX_OPSET)])
    model.ir_version = ONNX_IR_VERSION
    if metadata is not None:
        helper.set_model_props(model, metadata.to_props())
    onnx.checker.check_model(model)
    return model


def save(model: onnx.ModelProto, path: Path) -> Path:
    onnx.save(model, str(path))
    return path


def fixed_detector(boxes: np.ndarray, scores: np.ndarray, metadata: DetectorMetadata | None,
                   brightness_gate: bool = False) -> onnx.ModelProto:
    """A detector graph whose outputs are the given ``boxes`` ``(L, 4)`` (input pixels) and ``scores`` ``(L, C)``;
    with ``brightness_gate`` the scores are multiplied by the frame's mean brightness (a black frame finds
    nothing), so tests see the frame reach the network."""
    width = metadata.input_width if metadata is not None else 64
    height = metadata.input_height if metadata is not None else 48
    nodes = [helper.make_node("Identity", ["B"], [DETECTOR_BOXES])]
    if brightness_gate:
        nodes += [helper.make_node("ReduceMean", [DETECTOR_INPUT], ["mean"], keepdims=0),
                  helper.make_node("Mul", ["S", "mean"], [DETECTOR_SCORES])]
    else:
        nodes += [helper.make_node("Identity", ["S"], [DETECTOR_SCORES]),
                  helper.make_node("ReduceMean", [DETECTOR_INPUT], ["unused"], keepdims=0)]
    graph = helper.make_graph(
        nodes, "popcode_test_detector",
        [helper.make_tensor_value_info(DETECTOR_INPUT, TensorProto.FLOAT, [1, 1, height, width])],
        [helper.make_tensor_value_info(DETECTOR_BOXES, TensorProto.FLOAT, [1, len(boxes), 4]),
         helper.make_tensor_value_info(DETECTOR_SCORES, TensorProto.FLOAT, [1, len(boxes), scores.shape[1]])],
        initializer=[numpy_helper.from_array(np.asarray(boxes, np.float32)[None], "B"),
                     numpy_helper.from_array(np.asarray(scores, np.float32)[None], "S")],
    )
    return _checked_model(graph, metadata)
