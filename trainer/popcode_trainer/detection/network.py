"""The detector's network: torchvision's FCOS (anchor-free, one box per feature-map place) over a small plain
backbone and torchvision's feature pyramid, trained from scratch (no pretrained weights can be fetched here).

FCOS rather than a two-stage or anchor-based model: nothing to tune per dataset (anchor shapes), its losses and
target assignment are torchvision's, and its whole forward pass is a convolution graph, so the export
(:mod:`popcode_trainer.detection.export`) is the network plus a box decoding, with thresholds and NMS left to the
runtime.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
from torch import nn

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.model.detector_metadata import DETECTOR_INPUT_MEAN

from .config import DetectorConfig

CLASS_LOGITS = "head.classification_head.cls_logits."  # the one layer tied to a detector's own objects
ANCHOR_SIZES = ((8,), (16,), (32,))  # FCOS's size per level = its stride: P3, P4, P5
IMAGE_MEAN, IMAGE_STD = (DETECTOR_INPUT_MEAN,), (0.25,)  # grey frames in [0, 1]


def _conv(fan_in: int, fan_out: int, stride: int) -> list[nn.Module]:
    return [nn.Conv2d(fan_in, fan_out, 3, stride, 1, bias=False), nn.BatchNorm2d(fan_out), nn.ReLU(inplace=True)]


class FrameBackbone(nn.Module):
    """Five stages of two 3x3 convolutions (the first of each strided), then a feature pyramid over strides 8, 16
    and 32: the levels FCOS reads."""

    def __init__(self, widths: tuple[int, ...], fpn_channels: int) -> None:
        from torchvision.ops import FeaturePyramidNetwork

        super().__init__()
        stages, fan_in = [], 1
        for width in widths:
            stages.append(nn.Sequential(*_conv(fan_in, width, 2), *_conv(width, width, 1)))
            fan_in = width
        self.stages = nn.ModuleList(stages)
        self.fpn = FeaturePyramidNetwork(list(widths[2:]), fpn_channels)
        self.out_channels = fpn_channels

    def forward(self, images: torch.Tensor) -> OrderedDict[str, torch.Tensor]:
        features, x = OrderedDict(), images
        for index, stage in enumerate(self.stages):
            x = stage(x)
            if index >= 2:
                features[f"p{index + 1}"] = x
        return self.fpn(features)


def build_detector(config: DetectorConfig, num_classes: int) -> nn.Module:
    """An FCOS detector of ``num_classes`` objects for grey frames of the config's size (no resizing inside)."""
    from torchvision.models.detection import FCOS
    from torchvision.models.detection.anchor_utils import AnchorGenerator
    from torchvision.models.detection.fcos import FCOSHead

    torch.manual_seed(config.seed)
    backbone = FrameBackbone(config.widths, config.fpn_channels)
    anchors = AnchorGenerator(ANCHOR_SIZES, ((1.0,),) * len(ANCHOR_SIZES))
    head = FCOSHead(config.fpn_channels, anchors.num_anchors_per_location()[0], num_classes, config.head_convs)
    return FCOS(backbone, num_classes, min_size=min(config.input_width, config.input_height),
                max_size=max(config.input_width, config.input_height), image_mean=list(IMAGE_MEAN),
                image_std=list(IMAGE_STD), anchor_generator=anchors, head=head,
                score_thresh=config.score_threshold, nms_thresh=config.nms_iou,
                detections_per_img=config.max_detections)


def transferable_weights(model: nn.Module) -> dict[str, torch.Tensor]:
    """A detector's weights that another detector of the same network but other objects can start from: all but
    the classification logits."""
    return {name: tensor.detach().cpu().clone() for name, tensor in model.state_dict().items()
            if not name.startswith(CLASS_LOGITS)}


def apply_detector_start(model: nn.Module, weights: dict[str, torch.Tensor], source: str) -> int:
    """Copy a start's weights (:func:`transferable_weights` of another detector) into ``model``; returns how many
    tensors were copied. A start of another network is refused in one line, naming a tensor that differs."""
    own = model.state_dict()
    expected = {name for name in own if not name.startswith(CLASS_LOGITS)}
    if set(weights) != expected:
        differing = sorted(set(weights) ^ expected)[0]
        raise PopcodeError(f"{source} is a start of another detector network ({differing} is in one and not the "
                           "other): give a start of this network or none")
    for name in expected:
        if weights[name].shape != own[name].shape:
            raise PopcodeError(f"{source} is a start of another detector network ({name} is "
                               f"{tuple(weights[name].shape)} there, {tuple(own[name].shape)} here)")
    model.load_state_dict(weights, strict=False)
    return len(expected)
