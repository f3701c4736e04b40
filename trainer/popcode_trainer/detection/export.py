"""Detector checkpoint -> ONNX file of docs/design.md#detector-contract, with its metadata, checked by a run of
the runtime's :class:`~popcode_runtime.inference.detector.Detector` against torch on held-out frames.

The graph is the network and its box decoding (torchvision's own coder over anchors fixed by the input size);
thresholds and NMS are left to the runtime, so a user can change them without exporting again.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import torch
from torch import nn

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.model.detector_metadata import (
    DETECTOR_BOXES,
    DETECTOR_INPUT,
    DETECTOR_SCORES,
    DetectorMetadata,
)

from ..export.model_io import save_onnx
from ..export.onnx_export import ONNX_OPSET
from ..train.checkpoint import git_revision, load
from .config import DetectorConfig
from .network import IMAGE_MEAN, IMAGE_STD, build_detector

PARITY_TOLERANCE = 1e-3  # scores and box edges (px) of onnxruntime against torch


class ExportedDetector(nn.Module):
    """The FCOS network over one normalised frame, returning decoded boxes ``(1, L, 4)`` and per-object scores
    ``(1, L, C)`` (FCOS's score: the square root of class probability times centre-ness)."""

    def __init__(self, model: nn.Module, config: DetectorConfig) -> None:
        from torchvision.models.detection.image_list import ImageList

        super().__init__()
        self.backbone, self.head = model.backbone, model.head
        frame = torch.zeros(1, 1, config.input_height, config.input_width)
        with torch.no_grad():
            features = list(model.eval().backbone(frame).values())
        anchors = model.anchor_generator(ImageList(frame, [frame.shape[-2:]]), features)[0]
        self.register_buffer("anchors", anchors)
        self.register_buffer("mean", torch.tensor(IMAGE_MEAN).view(1, -1, 1, 1))
        self.register_buffer("std", torch.tensor(IMAGE_STD).view(1, -1, 1, 1))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = list(self.backbone((image - self.mean) / self.std).values())
        out = self.head(features)
        boxes = self.head.box_coder.decode(out["bbox_regression"][0], self.anchors)
        scores = torch.sqrt(torch.sigmoid(out["cls_logits"][0]) * torch.sigmoid(out["bbox_ctrness"][0]))
        return boxes[None], scores[None]


def detector_metadata(state: dict[str, Any], config: DetectorConfig, averaged: bool = False) -> DetectorMetadata:
    """What the file says of itself: objects, input size, default thresholds and what it was trained on."""
    training = {"config": config.to_dict(), "epochs": int(state["epoch"]), "frames": state.get("frames", {}),
                "weights": "moving average of the steps" if averaged else "the last step's",
                "architecture": "torchvision FCOS, plain backbone + FPN (P3-P5)",
                "first_weights": str(state.get("start", "random weights (a run of an older trainer)")),
                "git_revision": git_revision()}
    return DetectorMetadata(tuple(state["obj_ids"]), config.input_width, config.input_height,
                            config.score_threshold, config.nms_iou, config.max_detections, training)


def load_detector(checkpoint: str | Path, averaged: bool = True) -> tuple[nn.Module, DetectorConfig, dict[str, Any]]:
    """The trained network of a detector checkpoint, its config and the checkpoint's state; the moving average of
    its weights where the run kept one (``detector.ema_decay``) unless not ``averaged``."""
    state = load(checkpoint)
    missing = {"model", "config", "obj_ids", "epoch"} - set(state)
    if missing:
        raise PopcodeError(f"{checkpoint} is not a detector checkpoint (it lacks {sorted(missing)}); pose model "
                           "checkpoints export with popcode-train export")
    config = DetectorConfig.from_dict(state["config"])
    model = build_detector(config, len(state["obj_ids"]))
    model.load_state_dict(state["ema"]["weights"] if averaged and "ema" in state else state["model"])
    return model.eval(), config, state


def export_detector(checkpoint: str | Path, out_path: str | Path, check_frames: np.ndarray | None = None,
                    averaged: bool = True) -> Path:
    """Write ``out_path`` from ``checkpoint`` (its averaged weights where it has them, unless not ``averaged``);
    ``check_frames`` ``(N, H, W)`` in [0, 1] (default: noise) are run through torch and onnxruntime, which must
    agree."""
    model, config, state = load_detector(checkpoint, averaged)
    exported = ExportedDetector(model, config).eval()
    frame = torch.zeros(1, 1, config.input_height, config.input_width)
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as folder:
        raw = Path(folder) / "raw.onnx"
        with warnings.catch_warnings():  # the TorchScript exporter, chosen as for the pose models
            warnings.simplefilter("ignore")
            torch.onnx.export(exported, (frame,), str(raw), input_names=[DETECTOR_INPUT],
                              output_names=[DETECTOR_BOXES, DETECTOR_SCORES], opset_version=ONNX_OPSET,
                              do_constant_folding=True, dynamo=False)
        graph = onnx.load(str(raw))
    save_onnx(graph, detector_metadata(state, config, averaged and "ema" in state), out_path)
    _check_parity(exported, out_path, config, check_frames)
    return out_path


def _check_parity(exported: nn.Module, path: Path, config: DetectorConfig, frames: np.ndarray | None) -> None:
    from popcode_runtime.model.engine import onnx_session

    if frames is None:
        frames = np.random.default_rng(0).random((2, config.input_height, config.input_width), np.float32)
    session = onnx_session(path)
    for frame in frames.astype(np.float32):
        with torch.no_grad():
            boxes, scores = (t.numpy() for t in exported(torch.from_numpy(frame)[None, None]))
        got_boxes, got_scores = session.run([DETECTOR_BOXES, DETECTOR_SCORES], {DETECTOR_INPUT: frame[None, None]})
        worst = max(np.abs(got_scores - scores).max(), np.abs(got_boxes - boxes).max() / 100.0)
        if not worst <= PARITY_TOLERANCE:
            path.unlink(missing_ok=True)
            raise PopcodeError(f"the exported detector differs from torch by {worst:.3g} (scores, box px / 100): "
                               "not written")
