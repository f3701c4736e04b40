"""Checkpoint -> ONNX model meeting DESIGN section 3, checked, optionally quantised.

The float model is checked twice: ``onnx.checker`` on the graph and a parity
run (onnxruntime vs torch on the same crops: max absolute difference, argmax
identical). Quantised models are written beside it, each with its argmax and
pose agreement against the float model; all carry the same metadata.
"""

from __future__ import annotations

import copy
import logging
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch
from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

from popcode_runtime.decoding import decode_output
from popcode_runtime.errors import PopcodeError
from popcode_runtime.hypotheses import argmax_tolerance_rad, same_pose
from popcode_runtime.metadata import INPUT_NAME, OUTPUT_NAME, ModelMetadata
from popcode_runtime.symmetries import symmetry_rotations

from .model_io import load_checkpoint_model, save_onnx
from .network import ColumnBlockOutputLayer

ONNX_OPSET = 17
COREML_MAX_DIM = 16384  # onnxruntime's CoreML provider rejects larger tensor dimensions
QUANTISATIONS = ("int8", "nbits4", "nbits8")
NBITS_BLOCK_SIZE = 32
INT8_OP_TYPES = ("Conv", "Gemm", "MatMul")


@dataclass(frozen=True)
class Comparison:
    """How closely one model's outputs follow a reference on the same crops.

    The argmax agreement undercounts for symmetric objects: their code has a
    near-equal peak per equivalent pose, and tiny changes swap which is the
    highest. The pose agreement (:func:`pose_agreement`) counts those crops
    as agreeing; it is None where it cannot be measured (crops of unknown
    objects for a model whose objects differ in symmetry).
    """

    path: Path
    max_abs_diff: float
    argmax_agreement: float  # share of crops with the same argmax, in [0, 1]
    pose_agreement: float | None  # share of crops decoded to the same pose up to symmetry, in [0, 1]


def export_onnx(model: torch.nn.Module, metadata: ModelMetadata, out_path: str | Path,
                split_output: int = 0) -> Path:
    """Write the float ONNX model: input ``image`` [N, 1, S, S], output ``code`` [N, D].

    ``split_output`` > 0 computes the output layer in column blocks of at most
    that many outputs (CoreML accepts at most 16384).
    """
    out_path = Path(out_path)
    if split_output < 0 or split_output > COREML_MAX_DIM:
        raise PopcodeError(f"--split-output must lie in 1..{COREML_MAX_DIM} (0: no split), got {split_output}")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    size = metadata.input_size
    if split_output and split_output < metadata.output_dim:
        model = copy.deepcopy(model)
        model.head = ColumnBlockOutputLayer(model.head, split_output)
    with tempfile.TemporaryDirectory() as folder:
        raw = Path(folder) / "raw.onnx"
        # The TorchScript exporter is chosen on purpose (plain MatMul + Add graph, no extra
        # dependencies); its deprecation notice is not something a user can act on.
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.onnx.export(
                model.eval(), (torch.zeros(2, 1, size, size),), str(raw), input_names=[INPUT_NAME],
                output_names=[OUTPUT_NAME], dynamic_axes={INPUT_NAME: {0: "N"}, OUTPUT_NAME: {0: "N"}},
                opset_version=ONNX_OPSET, do_constant_folding=True, dynamo=False,
            )
        onnx_model = onnx.load(str(raw))
    save_onnx(onnx_model, metadata, out_path)
    return out_path


def run_onnx(path: str | Path, crops: np.ndarray) -> np.ndarray:
    options = ort.SessionOptions()
    options.log_severity_level = 3
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    return session.run([OUTPUT_NAME], {INPUT_NAME: np.ascontiguousarray(crops, dtype=np.float32)})[0]


def crop_symmetries(metadata: ModelMetadata, count: int,
                    obj_ids: Sequence[int] | None = None) -> list[np.ndarray] | None:
    """The symmetry rotations ``(K, 3, 3)`` of each of ``count`` crops' objects, from the model's metadata.

    Without ``obj_ids`` the crops may be of any of the model's objects: fine
    when they all share one set of symmetries (a one-object model), else None.
    """
    if obj_ids is None:
        first, *others = (symmetry_rotations(info) for info in metadata.objects.values())
        if any(S.shape != first.shape or not np.allclose(S, first) for S in others):
            return None
        return [first] * count
    ids = [int(i) for i in np.asarray(obj_ids).reshape(-1)]
    if len(ids) != count:
        raise PopcodeError(f"got {len(ids)} object ids for {count} crops")
    unknown = sorted(set(ids) - set(metadata.objects))
    if unknown:
        raise PopcodeError(f"crop object ids {unknown} are not in this model (it knows {sorted(metadata.objects)})")
    by_object = {obj_id: symmetry_rotations(info) for obj_id, info in metadata.objects.items()}
    return [by_object[i] for i in ids]


def pose_agreement(output: np.ndarray, reference: np.ndarray, metadata: ModelMetadata,
                   obj_ids: Sequence[int] | None = None) -> float | None:
    """Share of crops whose two outputs decode to the same pose up to the crop object's symmetries, in [0, 1].

    Both go through the runtime's argmax decoder (``decode_output``); the
    rotations are the same pose when :func:`~popcode_runtime.hypotheses.same_pose`
    holds within :func:`~popcode_runtime.hypotheses.argmax_tolerance_rad` of
    the model's code grid (one grid step per coordinate: what separates the
    argmax decodes of one pose's equivalent peaks). Axis-only codes compare
    the symmetry-axis direction. None when the crops' objects are needed but
    unknown (see :func:`crop_symmetries`).
    """
    symmetries = crop_symmetries(metadata, len(output), obj_ids)
    if symmetries is None:
        return None
    tolerance = argmax_tolerance_rad(metadata.code)
    R_output, R_reference = decode_output(output, metadata).R, decode_output(reference, metadata).R
    same = [same_pose(metadata.code, R_a, R_b, S, tolerance)
            for R_a, R_b, S in zip(R_output, R_reference, symmetries, strict=True)]
    return float(np.mean(same))


def compare(path: Path, output: np.ndarray, reference: np.ndarray, metadata: ModelMetadata,
            obj_ids: Sequence[int] | None = None) -> Comparison:
    """``output`` against ``reference`` (both ``(N, D)``, same crops); ``obj_ids``: each crop's object."""
    return Comparison(path=path, max_abs_diff=float(np.abs(output - reference).max()),
                      argmax_agreement=float(np.mean(output.argmax(1) == reference.argmax(1))),
                      pose_agreement=pose_agreement(output, reference, metadata, obj_ids))


def check_parity(model: torch.nn.Module, onnx_path: Path, crops: np.ndarray, metadata: ModelMetadata,
                 obj_ids: Sequence[int] | None = None) -> tuple[Comparison, np.ndarray]:
    """onnxruntime vs torch on ``crops``; refuses an export whose argmax differs anywhere."""
    with torch.no_grad():
        reference = model.eval()(torch.from_numpy(np.asarray(crops, np.float32))).numpy()
    result = compare(onnx_path, run_onnx(onnx_path, crops), reference, metadata, obj_ids)
    if result.argmax_agreement < 1.0:
        raise PopcodeError(f"{onnx_path}: onnxruntime and torch disagree on the argmax of "
                           f"{100 * (1 - result.argmax_agreement):.1f}% of the crops "
                           f"(max abs diff {result.max_abs_diff:.3g}); the export is wrong")
    return result, reference


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
    in float on dequantised weights (on the paper network: 9.5 ms of 19).
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


def _quantise_int8(float_path: Path, out_path: Path, calibration: np.ndarray) -> onnx.ModelProto:
    """Static QDQ int8 of every Conv, Gemm and MatMul, ranges calibrated on ``calibration`` crops."""
    with tempfile.TemporaryDirectory() as folder:
        inlined = Path(folder) / "inlined.onnx"
        onnx.save(_inline_identity_initializers(onnx.load(str(float_path))), str(inlined))
        logging.disable(logging.WARNING)  # "consider pre-processing": done above, nothing left to act on
        try:
            quantize_static(inlined, out_path, _Calibration(calibration), quant_format=QuantFormat.QDQ,
                            op_types_to_quantize=list(INT8_OP_TYPES), per_channel=True, reduce_range=True,
                            activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8)
        finally:
            logging.disable(logging.NOTSET)
    return onnx.load(str(out_path))


def quantise(float_path: Path, kind: str, metadata: ModelMetadata, calibration: np.ndarray | None = None) -> Path:
    """Write ``<name>.<kind>.onnx`` beside the float model, with the same metadata.

    int8: static QDQ quantisation (onnxruntime ``quantize_static``) of every
    Conv, Gemm and MatMul: per-channel int8 weights (7-bit, ``reduce_range``,
    so CPUs without VNNI cannot saturate), uint8 activations whose ranges
    come from ``calibration`` crops (required). The contrast normalisation
    stays float. Chosen by measurement on the paper network (random weights,
    1 thread, 2-core AMD EPYC with AVX-512 VNNI; fp32 31 ms): dynamic
    quantisation of all ops (ConvInteger) 126 ms; dynamic restricted to
    MatMul/Gemm 27-30 ms, since the float convolutions are 77 % of the time;
    static QDQ of the convolutions only 13 ms; static QDQ of all 9-10 ms,
    argmax agreement with fp32 100 % on held-out rendered crops.
    nbits4/nbits8: weight-only ``MatMulNBits`` (blocks of 32) on the MatMul
    nodes, i.e. the large output layer; the rest stays float.
    """
    if kind not in QUANTISATIONS:
        raise PopcodeError(f"unknown quantisation {kind!r}; choose from {list(QUANTISATIONS)}")
    out_path = float_path.with_name(f"{float_path.stem}.{kind}.onnx")
    if kind == "int8":
        if calibration is None or len(calibration) == 0:
            raise PopcodeError("int8 quantisation needs calibration crops float32 [N, 1, S, S] (N >= 1)")
        quantised = _quantise_int8(float_path, out_path, calibration)
    else:
        from onnxruntime.quantization.matmul_nbits_quantizer import MatMulNBitsQuantizer

        quantiser = MatMulNBitsQuantizer(onnx.load(str(float_path)), bits=int(kind[len("nbits"):]),
                                         block_size=NBITS_BLOCK_SIZE, is_symmetric=True,
                                         op_types_to_quantize=("MatMul",))
        quantiser.process()
        quantised = quantiser.model.model
    save_onnx(quantised, metadata, out_path)
    return out_path


def export_checkpoint(checkpoint_path: str | Path, out_path: str | Path, crops: np.ndarray,
                      quantisations: tuple[str, ...] = (), split_output: int = 0,
                      obj_ids: Sequence[int] | None = None) -> list[Comparison]:
    """Export, check parity, quantise; returns the float parity and each quantised model's agreement.

    int8 is calibrated on ``crops`` too, so its agreement is measured on the
    crops it was calibrated on. ``obj_ids`` (the object of each crop) picks
    each crop's symmetries for the pose agreement; a model of several objects
    with different symmetries has none without them.
    """
    model, metadata = load_checkpoint_model(checkpoint_path)
    size = metadata.input_size
    crops = np.asarray(crops, dtype=np.float32)
    if crops.ndim != 4 or crops.shape[1:] != (1, size, size) or len(crops) == 0:
        raise PopcodeError(f"parity crops must be float32 [N, 1, {size}, {size}], got {crops.shape}")
    crop_symmetries(metadata, len(crops), obj_ids)  # bad object ids are refused before anything is written
    float_path = export_onnx(model, metadata, out_path, split_output)
    parity, reference = check_parity(model, float_path, crops, metadata, obj_ids)
    results = [parity]
    for kind in quantisations:
        path = quantise(float_path, kind, metadata, calibration=crops)
        results.append(compare(path, run_onnx(path, crops), reference, metadata, obj_ids))
    return results
