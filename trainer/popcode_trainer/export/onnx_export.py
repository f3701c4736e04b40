"""Checkpoint -> ONNX model meeting docs/design.md#model-contract, checked, optionally quantised.

The float model is checked twice: ``onnx.checker`` on the graph and a parity
run (onnxruntime vs torch on the same crops: max absolute difference, argmax
identical). Quantised models are written beside it, each with its argmax and
pose agreement against the float model; all carry the same metadata.
"""

from __future__ import annotations

import copy
import dataclasses
import tempfile
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import onnx
import torch

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.coding.confidence import Calibrator
from popcode_runtime.model.engine import OnnxEngine
from popcode_runtime.model.metadata import INPUT_NAME, OUTPUT_NAME, ModelMetadata

from ..train.network import ColumnBlockOutputLayer
from .agreement import Comparison, compare, crop_symmetries
from .model_io import TrainedModel, load_trained_model, save_onnx
from .quantise import quantise
from .torch_engine import TorchEngine

ONNX_OPSET = 17
COREML_MAX_DIM = 16384  # onnxruntime's CoreML provider rejects larger tensor dimensions


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


def check_parity(model: torch.nn.Module, onnx_path: Path, crops: np.ndarray, metadata: ModelMetadata,
                 obj_ids: Sequence[int] | None = None) -> tuple[Comparison, np.ndarray]:
    """onnxruntime vs torch on ``crops`` (both as the runtime's engines); refuses an export whose argmax differs
    anywhere. Returns the comparison and torch's outputs."""
    reference = TorchEngine(model)(crops)
    result = compare(onnx_path, OnnxEngine(onnx_path)(crops), reference, metadata, obj_ids)
    if result.argmax_agreement < 1.0:
        raise PopcodeError(f"{onnx_path}: onnxruntime and torch disagree on the argmax of "
                           f"{100 * (1 - result.argmax_agreement):.1f}% of the crops "
                           f"(max abs diff {result.max_abs_diff:.3g}); the export is wrong")
    return result, reference


def export_checkpoint(checkpoint_path: str | Path, out_path: str | Path, crops: np.ndarray,
                      quantisations: tuple[str, ...] = (), split_output: int = 0,
                      obj_ids: Sequence[int] | None = None, calibrator: Calibrator | None = None) -> list[Comparison]:
    """:func:`export_trained` of the training checkpoint at ``checkpoint_path``."""
    return export_trained(load_trained_model(checkpoint_path), out_path, crops, quantisations, split_output, obj_ids,
                          calibrator)


def export_trained(trained: TrainedModel, out_path: str | Path, crops: np.ndarray, quantisations: tuple[str, ...] = (),
                   split_output: int = 0, obj_ids: Sequence[int] | None = None,
                   calibrator: Calibrator | None = None) -> list[Comparison]:
    """Export a loaded checkpoint, check parity, quantise; returns the float parity and each quantised model's
    agreement.

    int8 is calibrated on ``crops`` too, so its agreement is measured on the
    crops it was calibrated on. ``obj_ids`` (the object of each crop) picks
    each crop's symmetries for the pose agreement; a model of several objects
    with different symmetries has none without them. ``calibrator`` (see
    :mod:`popcode_trainer.export.confidence_fit`) goes into the metadata of every model written.
    """
    model = trained.network
    metadata = dataclasses.replace(trained.metadata, confidence=calibrator)
    size = metadata.input_size
    crops = np.asarray(crops, dtype=np.float32)
    if crops.ndim != 4 or crops.shape[1:] != (1, size, size) or len(crops) == 0:
        raise PopcodeError(f"parity crops must be float32 [N, 1, {size}, {size}], got {crops.shape}")
    crop_symmetries(metadata, len(crops), obj_ids)  # bad object ids are refused before anything is written
    float_path = export_onnx(model, metadata, out_path, split_output)
    try:
        parity, reference = check_parity(model, float_path, crops, metadata, obj_ids)
    except PopcodeError:
        float_path.unlink(missing_ok=True)  # a model that failed its check must not look finished
        raise
    results = [parity]
    for kind in quantisations:
        path = quantise(float_path, kind, metadata, calibration=crops)
        results.append(compare(path, OnnxEngine(path)(crops), reference, metadata, obj_ids))
    return results
