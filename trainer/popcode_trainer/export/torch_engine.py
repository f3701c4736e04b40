"""A torch network as an inference engine of the runtime, so checkpoints run through the one pipeline.

``PoseEstimator.from_engine(TorchEngine(network), metadata)`` crops, decodes
and converts frames exactly as for the exported ONNX model; only the network
call differs (see :mod:`popcode_runtime.model.engine`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from popcode_runtime.inference.estimator import PoseEstimator

from .model_io import TrainedModel, load_trained_model


class TorchEngine:
    """``engine(crops) -> outputs``: a network in eval mode under ``torch.no_grad()``, on the CPU, numpy out."""

    def __init__(self, network: torch.nn.Module) -> None:
        self.network = network.eval()

    def __call__(self, crops: np.ndarray) -> np.ndarray:
        """Outputs ``(N, D)`` float32 for crops ``(N, 1, S, S)`` (made contiguous float32 first)."""
        with torch.no_grad():
            return self.network(torch.from_numpy(np.ascontiguousarray(crops, dtype=np.float32))).numpy()


def trained_estimator(trained: TrainedModel, decoder: str = "argmax") -> PoseEstimator:
    """A loaded checkpoint as a ``PoseEstimator``: its network through torch, its metadata as export writes it."""
    return PoseEstimator.from_engine(TorchEngine(trained.network), trained.metadata, decoder)


def checkpoint_estimator(path: str | Path, decoder: str = "argmax") -> PoseEstimator:
    """The :func:`trained_estimator` of the training checkpoint at ``path``."""
    return trained_estimator(load_trained_model(path), decoder)
