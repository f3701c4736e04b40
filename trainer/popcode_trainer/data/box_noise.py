"""How a detector's boxes differ from the ground truth: a seeded noise model for training crops and evaluation.

A detector's box is the true box scaled (log-normal), shifted by a share of its size, stretched
in aspect (log-normal) and clipped to the image, since a detector never reports pixels outside
it (an object cut by the border gets a truncated box where ``bbox_obj`` would run past the edge).
Presets are named by the typical IoU with the true box they give; :func:`iou_statistics` measures
it, and ``bench/results/box-noise.md`` has the distribution of each preset.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from popcode_runtime.base.errors import PopcodeError

Box = tuple[float, float, float, float]  # x, y, w, h px


@dataclass(frozen=True)
class BoxNoise:
    """Spreads of a detector's error, each a standard deviation."""

    log_scale: float  # log of the box's size ratio to the true one (both sides alike)
    shift: float  # centre shift per axis as a share of the true box's side on that axis
    log_aspect: float  # log of the width/height stretch (width times e^a, height times e^-a)

    @property
    def is_none(self) -> bool:
        return self.log_scale == 0 and self.shift == 0 and self.log_aspect == 0

    def reach(self, deviations: float = 3.0) -> tuple[float, float]:
        """The largest size ratio and centre shift (share of the side) within ``deviations`` standard deviations."""
        return float(np.exp(deviations * (self.log_scale + self.log_aspect))), deviations * self.shift


BOX_NOISE_PRESETS: dict[str, BoxNoise] = {
    "none": BoxNoise(0.0, 0.0, 0.0),
    "tight": BoxNoise(0.04, 0.02, 0.03),  # a well-trained detector on clean images: IoU about 0.9
    "detector": BoxNoise(0.12, 0.06, 0.09),  # a typical detector in clutter: IoU about 0.75
    "loose": BoxNoise(0.22, 0.11, 0.15),  # a weak one: IoU about 0.6
}


def box_noise_preset(name: str) -> BoxNoise:
    """The named preset; an unknown name is an error listing the known ones."""
    if name not in BOX_NOISE_PRESETS:
        raise PopcodeError(f"unknown box-noise preset {name!r}; choose one of {list(BOX_NOISE_PRESETS)}")
    return BOX_NOISE_PRESETS[name]


def noisy_box(box: Sequence[float], noise: BoxNoise, rng: np.random.Generator,
              image_size: tuple[int, int] | None = None) -> Box:
    """One detector-like box for the true ``box``; ``image_size`` (width, height) clips it to the image.

    Always draws the same four numbers from ``rng``, whatever the preset, so a sample's later draws
    do not depend on it.
    """
    x, y, w, h = (float(v) for v in box)
    scale, shift_x, shift_y, aspect = rng.standard_normal(4)
    size = np.exp(noise.log_scale * scale)
    stretch = np.exp(noise.log_aspect * aspect)
    new_w, new_h = w * size * stretch, h * size / stretch
    cx, cy = x + w / 2 + noise.shift * shift_x * w, y + h / 2 + noise.shift * shift_y * h
    x0, y0, x1, y1 = cx - new_w / 2, cy - new_h / 2, cx + new_w / 2, cy + new_h / 2
    if image_size is not None:
        width, height = image_size
        x0, x1 = np.clip([x0, x1], 0.0, width)
        y0, y1 = np.clip([y0, y1], 0.0, height)
        if x1 - x0 < 1.0 or y1 - y0 < 1.0:  # clipped away: the detector would report the visible sliver
            return _clip_box(box, width, height)
    return float(x0), float(y0), float(x1 - x0), float(y1 - y0)


def _clip_box(box: Sequence[float], width: float, height: float) -> Box:
    x, y, w, h = (float(v) for v in box)
    x0, x1 = min(max(x, 0.0), width - 1.0), min(max(x + w, 1.0), width)
    y0, y1 = min(max(y, 0.0), height - 1.0), min(max(y + h, 1.0), height)
    return x0, y0, max(x1 - x0, 1.0), max(y1 - y0, 1.0)


def box_intersection(a: Sequence[float], b: Sequence[float]) -> float:
    """Area shared by two ``x, y, w, h`` boxes."""
    ax, ay, aw, ah = (float(v) for v in a)
    bx, by, bw, bh = (float(v) for v in b)
    return max(0.0, min(ax + aw, bx + bw) - max(ax, bx)) * max(0.0, min(ay + ah, by + bh) - max(ay, by))


def box_iou(a: Sequence[float], b: Sequence[float]) -> float:
    """Intersection over union of two ``x, y, w, h`` boxes."""
    inter = box_intersection(a, b)
    union = float(a[2]) * float(a[3]) + float(b[2]) * float(b[3]) - inter
    return inter / union if union > 0 else 0.0


def iou_statistics(noise: BoxNoise, draws: int = 4000, seed: int = 0) -> dict[str, float]:
    """Mean and quantiles of the IoU between a unit box and its noisy versions (no image border)."""
    rng = np.random.default_rng(seed)
    box = (0.0, 0.0, 100.0, 100.0)
    ious = np.array([box_iou(box, noisy_box(box, noise, rng)) for _ in range(draws)])
    return {"mean": float(ious.mean()), "p05": float(np.quantile(ious, 0.05)),
            "median": float(np.median(ious)), "p95": float(np.quantile(ious, 0.95))}


IOU_BINS = ((0.0, 0.5), (0.5, 0.65), (0.65, 0.8), (0.8, 0.9), (0.9, 1.01))


def iou_bin_label(low: float, high: float) -> str:
    return f"IoU {low:.2f}-{min(high, 1.0):.2f}"
