"""Model I/O: a training checkpoint -> network + metadata, and an ONNX graph + metadata -> a model file."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import onnx
import torch
from google.protobuf.message import DecodeError
from onnx import helper

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import write_bytes_atomic
from popcode_runtime.model.detector_metadata import DetectorMetadata
from popcode_runtime.model.metadata import ModelMetadata

from ..data.hull import with_hull_points
from ..train import checkpoint
from ..train.config import Config
from ..train.network import NetworkConfig, build_network
from ..train.representations import CodeSoftmax, code_mass

ONNX_IR_VERSION = 10  # onnx >= 1.23 writes IR 14, which current onnxruntime releases refuse


@dataclass(frozen=True)
class TrainedModel:
    """A training checkpoint read once (:func:`load_trained_model`) for everything a command does with it: export,
    quantisation, the torch engine and the confidence fit share its network and metadata."""

    network: torch.nn.Module  # eval mode, outputs what the runtime reads
    metadata: ModelMetadata  # training summary and hull points included

    @property
    def config(self) -> Config:
        """The training config, checked as a config file is; only where it is used (an old checkpoint's config may
        name settings since removed, which export alone does not need)."""
        return Config.from_dict(self.metadata.training["config"])


def load_trained_model(path: str | Path) -> TrainedModel:
    """The training checkpoint at ``path``, read once (see :func:`trained_model`)."""
    return trained_model(checkpoint.load_trained(path), path)


def trained_model(state: Mapping[str, Any], path: str | Path) -> TrainedModel:
    """The network (eval mode) and metadata of a checkpoint's contents (read from ``path`` by
    :func:`~popcode_trainer.train.checkpoint.load_trained`), training summary and hull points included.

    The network outputs what the runtime reads: a model trained with the
    cross-entropy loss gets its :class:`CodeSoftmax` appended.

    Each object's ``hull_points_mm`` were stored at training; a checkpoint
    written before they were gets them from its mesh in the training config's
    models folder (see :func:`~popcode_trainer.data.hull.with_hull_points`).
    """
    try:
        fields = {k: tuple(v) if isinstance(v, list) else v for k, v in state["network"].items()}
        model = build_network(NetworkConfig(**fields))
        model.load_state_dict(state["model"])
        metadata = ModelMetadata.from_props(state["metadata"])
    except (KeyError, TypeError, RuntimeError) as error:
        raise PopcodeError(f"{path} is not a popcode training checkpoint: {error}") from error
    config = state["config"]
    best_deg = float(state["best_val_error_deg"])  # inf without a validation split: JSON has no inf, say None
    training = {
        "dataset": {"splits": config["data"]["splits"], "obj_ids": config["data"]["obj_ids"]},
        "epochs": int(state["epoch"]),
        "git_revision": state.get("git_revision", "unknown"),
        "best_val_error_deg": best_deg if math.isfinite(best_deg) else None,
        "step_path": state.get("step_path"),  # how the step ran (train.fast_path); None before it was recorded
        "config": config,
    }
    if config["train"].get("loss", "mse") == "cross_entropy":  # trained on logits: deployed as a code
        model.output_activation = CodeSoftmax(code_mass(metadata.code))
    objects = with_hull_points(metadata.objects, config["data"].get("models_dir"))
    return TrainedModel(model.eval(), dataclasses.replace(metadata, objects=objects, training=training))


def load_checkpoint_model(path: str | Path) -> tuple[torch.nn.Module, ModelMetadata]:
    """The network and metadata of :func:`load_trained_model`."""
    trained = load_trained_model(path)
    return trained.network, trained.metadata


def save_onnx(model: onnx.ModelProto, metadata: ModelMetadata | DetectorMetadata, path: Path) -> None:
    """Pin the IR version onnxruntime reads, attach the metadata, check and save atomically (an interrupted
    export leaves no half-written model that a rerun would take for finished)."""
    model.ir_version = ONNX_IR_VERSION
    del model.metadata_props[:]
    helper.set_model_props(model, metadata.to_props())
    onnx.checker.check_model(model)
    write_bytes_atomic(path, model.SerializeToString())


def read_onnx_metadata(path: str | Path) -> ModelMetadata:
    """The popcode metadata of an exported model, read from the file without building an inference session (for
    reports that only need to know what a model is)."""
    try:
        model = onnx.load(str(path), load_external_data=False)
    except (OSError, DecodeError) as error:
        raise PopcodeError(f"{path}: not a readable ONNX model ({error})") from error
    return ModelMetadata.from_props({prop.key: prop.value for prop in model.metadata_props})
