"""Quantised copies of a float ONNX model: static int8 QDQ, weight-only n-bit output layers, half-precision
weights."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import numpy as np
import onnx
from onnx import helper, numpy_helper
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.model.metadata import INPUT_NAME, ModelMetadata

from .model_io import save_onnx

QUANTISATIONS = ("int8", "int8-nbits8", "nbits4", "nbits8", "fp16", "nbits8-fp16")
NBITS_BLOCK_SIZE = 32
# onnxruntime's MatMulNBits accuracy level 4: int8 activations in its integer kernels. At the default level the
# 8-bit output layer ran 3.5-4.5x slower than float on an AVX-512 EPYC, at the same agreement with float
# (bench/results/network-width.md).
NBITS_INT8_COMPUTE = 4
INT8_OP_TYPES = ("Conv", "Gemm", "MatMul")
TRUNK_OP_TYPES = ("Conv", "Gemm")  # int8-nbits8: the trunk and hidden layers; the output layer is a MatMul


class _Calibration(CalibrationDataReader):
    """Feeds crops to onnxruntime's calibrator in batches of 16 (its MinMax ranges)."""

    def __init__(self, crops: np.ndarray, batch: int = 16) -> None:
        self._batches = iter([{INPUT_NAME: np.ascontiguousarray(crops[i:i + batch], dtype=np.float32)}
                              for i in range(0, len(crops), batch)])

    def get_next(self) -> dict[str, np.ndarray] | None:
        return next(self._batches, None)


def _inline_identity_initializers(model: onnx.ModelProto) -> onnx.ModelProto:
    """Replace ``Identity(initializer)`` nodes by a copy of the initializer.

    The exporter shares equal initializers through Identity (an untrained
    network's folded BatchNorm biases are all zero); a conv whose bias is no
    initializer is not fused into ``QLinearConv`` by onnxruntime and runs
    in float on dequantised weights (measured: ``bench/results/quantisation.md``).
    """
    initializers = {init.name: init for init in model.graph.initializer}
    for node in list(model.graph.node):
        if node.op_type == "Identity" and node.input[0] in initializers:
            copied = onnx.TensorProto()
            copied.CopyFrom(initializers[node.input[0]])
            copied.name = node.output[0]
            model.graph.initializer.append(copied)
            model.graph.node.remove(node)
    return model


def _quantise_int8(model: onnx.ModelProto, calibration: np.ndarray,
                   op_types: tuple[str, ...] = INT8_OP_TYPES) -> onnx.ModelProto:
    """Static QDQ int8 of every node of ``op_types``, ranges calibrated on ``calibration`` crops.

    ``quantize_static`` writes its file in a scratch folder: only :func:`save_onnx`'s atomic
    rename puts a model at its final name.
    """
    with tempfile.TemporaryDirectory() as folder:
        inlined, out_path = Path(folder) / "inlined.onnx", Path(folder) / "int8.onnx"
        onnx.save(_inline_identity_initializers(model), str(inlined))
        logging.disable(logging.WARNING)  # "consider pre-processing": done above, nothing left to act on
        try:
            quantize_static(inlined, out_path, _Calibration(calibration), quant_format=QuantFormat.QDQ,
                            op_types_to_quantize=list(op_types), per_channel=True, reduce_range=True,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
        finally:
            logging.disable(logging.NOTSET)
        return onnx.load(str(out_path))


def _half_weights(model: onnx.ModelProto) -> onnx.ModelProto:
    """Store every float32 initializer as float16, read back through a ``Cast`` to float32.

    The graph computes in float32 as before: onnxruntime folds the casts of
    constants when the session starts, so the file halves and the speed stays
    fp32's. A tensor that float16 cannot hold (a value beyond its range) is
    refused rather than turned into inf.
    """
    half_max = float(np.finfo(np.float16).max)
    casts = []
    for init in model.graph.initializer:
        if init.data_type != onnx.TensorProto.FLOAT:
            continue
        values = numpy_helper.to_array(init)
        if values.size and float(np.abs(values).max()) > half_max:
            raise PopcodeError(f"initializer {init.name!r} holds values beyond float16's range "
                               f"({float(np.abs(values).max()):.3g}); keep this model in float32")
        name = init.name
        init.CopyFrom(numpy_helper.from_array(values.astype(np.float16), f"{name}.fp16"))
        casts.append(helper.make_node("Cast", [init.name], [name], to=onnx.TensorProto.FLOAT, name=f"{name}.to_float"))
    nodes = [*casts, *model.graph.node]
    del model.graph.node[:]
    model.graph.node.extend(nodes)
    return model


def _nbits_matmuls(model: onnx.ModelProto, bits: int) -> onnx.ModelProto:
    """Every MatMul's constant weight as ``MatMulNBits`` of ``bits`` bits in blocks of :data:`NBITS_BLOCK_SIZE`,
    computed on int8 activations (:data:`NBITS_INT8_COMPUTE`)."""
    from onnxruntime.quantization.matmul_nbits_quantizer import MatMulNBitsQuantizer

    quantiser = MatMulNBitsQuantizer(model, bits=bits, block_size=NBITS_BLOCK_SIZE, is_symmetric=True,
                                     accuracy_level=NBITS_INT8_COMPUTE, op_types_to_quantize=("MatMul",))
    logging.disable(logging.INFO)  # a line for every node it leaves alone
    try:
        quantiser.process()
    finally:
        logging.disable(logging.NOTSET)
    return quantiser.model.model


def quantised_path(float_path: Path, kind: str) -> Path:
    """Where the ``kind`` copy of a float model is written: beside it, ``<stem>.<kind>.onnx``."""
    return float_path.with_name(f"{float_path.stem}.{kind}.onnx")


def quantise(float_path: Path, kind: str, metadata: ModelMetadata, calibration: np.ndarray | None = None) -> Path:
    """Write ``<name>.<kind>.onnx`` beside the float model, with the same metadata.

    int8: static QDQ quantisation (onnxruntime ``quantize_static``) of every
    Conv, Gemm and MatMul: per-channel int8 weights (7-bit, ``reduce_range``,
    so CPUs without VNNI cannot saturate), uint8 activations whose ranges
    come from ``calibration`` crops (required). The contrast normalisation
    stays float. Chosen as the fastest variant that keeps the argmax of fp32
    (measured: bench/results/quantisation.md).
    int8-nbits8: the output layer as nbits8 (below), then static int8 of
    every Conv and Gemm as int8 does: the trunk at int8's speed, the large
    output layer on 8-bit blocks of 32 with a scale each instead of one range
    per output.
    nbits4/nbits8: ``MatMulNBits`` (blocks of 32, computed on int8
    activations: :data:`NBITS_INT8_COMPUTE`) on the MatMul nodes, i.e. the
    large output layer; the rest stays float.
    fp16: every weight stored in half precision and computed in float32
    (:func:`_half_weights`): half the file at float's speed and nearly its
    outputs, for a model too large to ship in float whose int8 copy loses
    accuracy (bench/results/shipped-models.md).
    nbits8-fp16: the output layer as nbits8, every other weight as fp16: for a wider
    trunk whose fp16 copy is over the repository's 8 MB, near float's scores
    and faster than float (bench/results/network-width.md).
    """
    if kind not in QUANTISATIONS:
        raise PopcodeError(f"unknown quantisation {kind!r}; choose from {list(QUANTISATIONS)}")
    out_path = quantised_path(float_path, kind)
    if kind.startswith("int8") and (calibration is None or len(calibration) == 0):
        raise PopcodeError(f"{kind} quantisation needs calibration crops float32 [N, 1, S, S] (N >= 1)")
    if kind == "int8":
        quantised = _quantise_int8(onnx.load(str(float_path)), calibration)
    elif kind == "int8-nbits8":
        quantised = _quantise_int8(_nbits_matmuls(onnx.load(str(float_path)), 8), calibration, TRUNK_OP_TYPES)
    elif kind == "fp16":
        quantised = _half_weights(onnx.load(str(float_path)))
    else:
        bits, _, rest = kind[len("nbits"):].partition("-")
        quantised = _nbits_matmuls(onnx.load(str(float_path)), int(bits))
        if rest == "fp16":
            quantised = _half_weights(quantised)
    save_onnx(quantised, metadata, out_path)
    return out_path
