"""Inference engines: any callable crops ``(N, 1, S, S)`` float32 -> network outputs ``(N, D)`` float32.

onnxruntime is the runtime's engine (:class:`OnnxEngine`); the trainer passes a
torch one to :meth:`~popcode_runtime.inference.estimator.PoseEstimator.from_engine` for
checkpoints. Every onnxruntime session of the project is built by
:func:`onnx_session`, so providers, threads and options are chosen in one place.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import onnxruntime as ort

from ..base.checks import integer, path
from ..base.errors import PopcodeError, library_step
from .metadata import INPUT_NAME, OUTPUT_NAME, ModelMetadata

UNBOUNDED_OPS = ("Loop",)
MAX_FIXED_BATCH = 1024  # crops a model's fixed batch axis may ask for (a box is padded to a whole batch)
Engine = Callable[[np.ndarray], np.ndarray]  # crops (N, 1, S, S) float32 in [0, 1] -> outputs (N, D) float32

PROVIDER_NAMES = {
    "cpu": "CPUExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "tensorrt": "TensorrtExecutionProvider",
    "coreml": "CoreMLExecutionProvider",
    "openvino": "OpenVINOExecutionProvider",
    "dml": "DmlExecutionProvider",
}


def resolve_providers(providers: Sequence[str] | None) -> list[str]:
    """Map short names (``cpu``, ``cuda``, ``coreml``...) to onnxruntime providers; CPU last.

    Asking for one this onnxruntime build lacks is an error, not a silent fallback.
    """
    if isinstance(providers, (str, bytes)) or not (providers is None or isinstance(providers, Sequence)):
        raise PopcodeError(f"providers must be a list of names such as ['cpu'], got {providers!r}")
    available = ort.get_available_providers()
    resolved = []
    for name in providers or ["cpu"]:
        if not isinstance(name, str):
            raise PopcodeError(f"a provider is a name such as 'cpu', got {name!r}")
        full = PROVIDER_NAMES.get(name.lower(), name)
        if full not in available:
            raise PopcodeError(
                f"execution provider {name!r} is not available in this onnxruntime build; "
                f"available: {', '.join(available)}"
            )
        resolved.append(full)
    if "CPUExecutionProvider" not in resolved:
        resolved.append("CPUExecutionProvider")
    return resolved


def onnx_session(model: str | Path | bytes, providers: Sequence[str] | None = None, threads: int = 0,
                 profile_prefix: str | None = None) -> ort.InferenceSession:
    """An onnxruntime session for a model file (or its serialised bytes), warnings silenced.

    ``threads`` sets the intra-op threads (0: onnxruntime's default, all
    cores); ``profile_prefix`` turns on onnxruntime's profiler, whose JSON
    ``session.end_profiling()`` writes under that prefix.
    """
    if not isinstance(model, bytes):
        model = path(model, "model path")
    name = "the given model bytes" if isinstance(model, bytes) else str(model)
    if not isinstance(model, bytes) and not model.is_file():
        raise PopcodeError(f"model file not found: {model}")
    check_threads(threads)
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.log_severity_level = 4  # fatal only: failures reach the user as one PopcodeError line, not C++ logs
    if profile_prefix is not None:
        options.enable_profiling = True
        options.profile_file_prefix = profile_prefix
    resolved = resolve_providers(providers)
    _refuse_unbounded_ops(model if isinstance(model, bytes) else model.read_bytes(), name)
    with library_step(f"load {name} as an ONNX model"):
        return ort.InferenceSession(model if isinstance(model, bytes) else str(model), options, providers=resolved)


def _refuse_unbounded_ops(data: bytes, name: str) -> None:
    """Refuse a graph whose run time its inputs do not bound: a ``Loop`` runs as often as a number in the model
    says (forever, for a crafted one). An op's type is stored as plain text after its field tag (protobuf field 4,
    length-delimited), so this needs no ONNX parser in the runtime; popcode's networks have no control flow."""
    for op in UNBOUNDED_OPS:
        if b"\x22" + bytes([len(op)]) + op.encode() in data:
            raise PopcodeError(f"{name}: the graph has a '{op}' op, whose run time nothing bounds; popcode models "
                               "are feed-forward networks")


def check_threads(threads: int) -> int:
    """Intra-op threads: 0 (all cores) up to this machine's core count; more only oversubscribe it."""
    threads = integer(threads, "threads")
    cores = os.cpu_count() or 1
    if threads < 0:
        raise PopcodeError(f"threads must be >= 0, got {threads}")
    if threads > cores:
        raise PopcodeError(f"threads {threads} is more than this machine's {cores} cores")
    return threads


def custom_metadata(session: ort.InferenceSession, model_path: Path) -> dict[str, str]:
    """A model file's ``metadata_props`` as onnxruntime reads them (a value that is not UTF-8 is named, not raised)."""
    with library_step(f"read the metadata of {model_path} (it must be UTF-8 JSON)"):
        return dict(session.get_modelmeta().custom_metadata_map)


class OnnxEngine:
    """A popcode ONNX model file run by onnxruntime; its metadata, checked against its signature, from the file."""

    def __init__(self, model_path: str | Path, providers: Sequence[str] | None = None, threads: int = 0) -> None:
        self.model_path = path(model_path, "model path")
        self.session = onnx_session(self.model_path, providers, threads)
        try:
            self.metadata = ModelMetadata.from_props(custom_metadata(self.session, self.model_path))
        except PopcodeError as error:
            raise PopcodeError(f"{self.model_path}: {error}") from error
        self.max_batch: int | None = None  # set when the model's batch axis is fixed
        self._check_signature()

    def _check_signature(self) -> None:
        inputs = {i.name: i for i in self.session.get_inputs()}
        outputs = {o.name: o for o in self.session.get_outputs()}
        if INPUT_NAME not in inputs or len(inputs) != 1:
            raise PopcodeError(f"model must have exactly one input named '{INPUT_NAME}', it has {sorted(inputs)}")
        if OUTPUT_NAME not in outputs:
            raise PopcodeError(f"model has no output named '{OUTPUT_NAME}' (outputs: {sorted(outputs)})")
        size = self.metadata.input_size
        shape = inputs[INPUT_NAME].shape
        if len(shape) != 4 or [d for d in shape[1:]] != [1, size, size]:
            raise PopcodeError(f"input '{INPUT_NAME}' must be [N, 1, {size}, {size}], the model declares {shape}")
        if isinstance(shape[0], int) and shape[0] > 0:
            if shape[0] > MAX_FIXED_BATCH:
                raise PopcodeError(f"input '{INPUT_NAME}' fixes the batch at {shape[0]} crops; at most "
                                   f"{MAX_FIXED_BATCH} (every call is padded to it, one box too)")
            self.max_batch = shape[0]  # a fixed batch axis: run in chunks of it
        if inputs[INPUT_NAME].type != "tensor(float)":
            raise PopcodeError(f"input '{INPUT_NAME}' must be float32, the model declares {inputs[INPUT_NAME].type}")
        self.metadata.check_output(outputs[OUTPUT_NAME].shape)

    @property
    def providers(self) -> list[str]:
        """The execution providers onnxruntime runs this model with, in order of preference."""
        return self.session.get_providers()

    def __call__(self, crops: np.ndarray) -> np.ndarray:
        """Outputs ``(N, D)`` for crops ``(N, 1, S, S)`` (made contiguous float32 first)."""
        with library_step(f"run {self.model_path} on {len(crops)} crops"):
            return self.session.run([OUTPUT_NAME], {INPUT_NAME: np.ascontiguousarray(crops, dtype=np.float32)})[0]
