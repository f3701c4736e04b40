"""Detector starts: a detector trained on bin scenes of many generated parts, whose weights but the classification
logits a detector of other parts starts from instead of random weights (``detector.init``; issue 52: the demo's
detector trains for minutes on a few scenes, from random weights it learns little; bench/results/detector-start.md).

The file format, its checks and the choice of ``detector.init`` ("auto", "none" or a start file) are the pose
models' (:mod:`popcode_trainer.train.pretrained`); what differs is which weights a start carries
(:func:`~popcode_trainer.detection.network.transferable_weights`) and the settings its shape is made of.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from torch import nn

from ..train.pretrained import PretrainedStart, StartKind, resolve_kind_start, save_start, shipped_start_path
from .config import DetectorConfig
from .network import apply_detector_start, transferable_weights

DETECTOR_START = StartKind("popcode-detector-start", "detector start", "python -m experiments.detector_start",
                           "detector-start", "detector", "detector.init")
SHAPE_FIELDS = ("input_width", "input_height", "widths", "fpn_channels", "head_convs")  # what the weights fit


def detector_shape(config: DetectorConfig) -> dict[str, Any]:
    """The settings a detector's transferable weights depend on."""
    settings = config.to_dict()
    return {key: settings[key] for key in SHAPE_FIELDS}


def shipped_detector_start(config: DetectorConfig, folder: Path | None = None) -> Path:
    """Where the shipped start of this detector shape lies (the repository's ``models/`` by default)."""
    return shipped_start_path(DETECTOR_START, detector_shape(config), folder)


def write_detector_start(model: nn.Module, config: DetectorConfig, path: Path, card: dict[str, Any]) -> Path:
    """Save a trained detector's transferable weights with ``card`` as a start, atomically."""
    return save_start(DETECTOR_START, detector_shape(config), transferable_weights(model), path, card)


def resolve_detector_start(config: DetectorConfig) -> tuple[PretrainedStart | None, str]:
    """The start ``config.init`` names, checked against ``config``'s shape, and one line saying which start."""
    return resolve_kind_start(config.init, detector_shape(config), DETECTOR_START)


def apply_start(model: nn.Module, start: PretrainedStart) -> int:
    """Copy the start's weights into ``model``; returns how many tensors were copied."""
    return apply_detector_start(model, start.state, str(start.path))
