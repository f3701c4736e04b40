"""What a detector is trained with: its input size, network width, optimisation and data; stored in every
checkpoint so that a resume with other settings is refused and the export records them.

The defaults are the choices measured on a validation split (bench/results/detector-choices.md).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.split import BOX_KINDS
from popcode_runtime.model.detector_metadata import MAX_DETECTIONS, MAX_SIDE, MIN_SIDE, DetectorMetadata

from ..train.config import typed_values

SIDE_MULTIPLE = 32  # the coarsest feature map's stride: the input must tile into it
MAX_WIDTH_CHANNELS = 512
MAX_DETECTOR_EPOCHS = 10_000
# Settings a resume may change: more epochs extend a run; the start only matters to a run's first epoch.
RESUMABLE = frozenset({"epochs", "init"})


@dataclass(frozen=True)
class DetectorConfig:
    """A detector's network and training. ``widths``: the backbone's stages (strides 2 to 32); the FCOS head and
    feature pyramid run at ``fpn_channels`` on strides 8, 16 and 32."""

    # 256 x 192 with one head convolution and the wider backbone: the best AP for the same minutes on a cluttered
    # validation split, 12 ms a frame on one core (bench/results/detector-choices.md)
    input_width: int = 256
    input_height: int = 192
    widths: tuple[int, ...] = (24, 48, 64, 96, 128)
    fpn_channels: int = 64
    head_convs: int = 1
    epochs: int = 30
    batch_size: int = 8
    lr: float = 2e-3
    weight_decay: float = 1e-4
    # The box it learns to draw: the whole object's (clipped to the image), the box BOP's 2-D detection scores by
    # default (the toolkit's amodal boxes) and the one the pose models are trained to crop.
    box_kind: str = "bbox_obj"
    min_visib_fract: float = 0.1  # less visible instances are no target (BOP19's threshold)
    val_fraction: float = 0.1  # of the training images, held out by image
    score_threshold: float = 0.3
    nms_iou: float = 0.5
    max_detections: int = 100
    seed: int = 0
    # the weights validated and exported: their moving average over the steps with this decay (0: the last step's;
    # detection/averaging.py)
    ema_decay: float = 0.0
    # of the training frames, the share replaced each epoch by a generated frame without parts (flat, noise,
    # gradients, textures): negatives besides the rendered empty bins of ``render --empty-share``
    negative_share: float = 0.0
    # first weights: "auto" (the shipped detector start of this network shape, else random weights), "none"
    # (random weights) or a detector start file (detection/start.py)
    init: str = "auto"

    def __post_init__(self) -> None:
        for side, name in ((self.input_width, "input_width"), (self.input_height, "input_height")):
            if (not isinstance(side, int) or not MIN_SIDE <= side <= MAX_SIDE or side % SIDE_MULTIPLE) \
                    or isinstance(side, bool):
                raise PopcodeError(f"detector {name} must be a multiple of {SIDE_MULTIPLE} in [{MIN_SIDE}, "
                                   f"{MAX_SIDE}], got {side!r}")
        if len(self.widths) != 5 or not all(isinstance(w, int) and 1 <= w <= MAX_WIDTH_CHANNELS for w in self.widths):
            raise PopcodeError(f"detector widths are 5 stage widths of 1 to {MAX_WIDTH_CHANNELS}, got {self.widths}")
        if self.fpn_channels % 32 or not 32 <= self.fpn_channels <= MAX_WIDTH_CHANNELS:
            raise PopcodeError(f"detector fpn_channels must be a multiple of 32 (the head's group norm) in [32, "
                               f"{MAX_WIDTH_CHANNELS}], got {self.fpn_channels}")
        if not 0 <= self.head_convs <= 8 or not 1 <= self.epochs <= MAX_DETECTOR_EPOCHS or \
                not 1 <= self.batch_size <= 256:
            raise PopcodeError(f"need 0 <= head_convs <= 8, 1 <= epochs <= {MAX_DETECTOR_EPOCHS} and "
                               f"1 <= batch_size <= 256, got {self.head_convs}, {self.epochs}, {self.batch_size}")
        if not (0 < self.lr <= 1 and 0 <= self.weight_decay <= 1 and 0 <= self.min_visib_fract <= 1
                and 0 <= self.val_fraction < 1 and 0 <= self.ema_decay < 1 and 0 <= self.negative_share <= 0.9):
            raise PopcodeError("need 0 < lr <= 1, 0 <= weight_decay <= 1, 0 <= min_visib_fract <= 1, "
                               "0 <= val_fraction < 1, 0 <= ema_decay < 1 and 0 <= negative_share <= 0.9")
        if not isinstance(self.init, str) or not self.init.strip():
            raise PopcodeError(f"detector init must be 'auto', 'none' or a start file, got {self.init!r}")
        if self.box_kind not in BOX_KINDS:
            raise PopcodeError(f"detector box_kind must be one of {list(BOX_KINDS)}, got {self.box_kind!r}")
        DetectorMetadata.check_thresholds(self.score_threshold, self.nms_iou, self.max_detections)
        if self.max_detections > MAX_DETECTIONS:
            raise PopcodeError(f"max_detections at most {MAX_DETECTIONS}")

    def to_dict(self) -> dict[str, Any]:
        return {key: list(value) if isinstance(value, tuple) else value
                for key, value in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DetectorConfig:
        """A config of ``data`` (a checkpoint's, or the defaults with ``--set`` values), each value checked against
        its field's type as the pose model's settings are, then its range."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise PopcodeError(f"unknown detector setting(s) {unknown}; valid: {sorted(names)}")
        return cls(**typed_values(cls, data, "detector"))

    def with_overrides(self, overrides: dict[str, Any]) -> DetectorConfig:
        """This config with ``overrides`` (``--set key=value`` already parsed) applied and checked."""
        return DetectorConfig.from_dict({**self.to_dict(), **overrides})

    def differences(self, other: DetectorConfig) -> list[str]:
        """The settings that differ from ``other`` and a resume may not change."""
        mine, theirs = self.to_dict(), other.to_dict()
        return [key for key in mine if mine[key] != theirs[key] and key not in RESUMABLE]
