"""The paper's 1-D task (section IV-A, Table I): images of bars and arrows at an orientation, the square image's
symmetries that move them exactly, and the errors the paper reports; ``bench.toy_orientation`` trains on them.

Generator (ours; the paper shows examples only): a 64x64 black image with one
white shape drawn by cv2 with anti-aliasing, orientation uniform in [0, 360). A
bar is a filled rectangle of length 16..36 px and width 3..7 px (180 deg
symmetric); an arrow is a shaft of the same kind whose front end carries a
filled triangular head 8..12 px long that stands out 3..6 px beyond the shaft
on each side (not symmetric). The centre is uniform within +-8 px of the image
centre, less where the shape would then cross the border: the paper's shapes
lie inside the image, and an arrow whose head is cut off is a bar, whose
direction no network can know (an earlier generator let ~1 % of the heads leave
the image, and a single reversed test arrow adds ~160 deg^2 to a run's mean).
Angles are counter-clockwise from the image's +x axis with y up.
"""

from __future__ import annotations

import cv2
import numpy as np

IMAGE_SIZE = 64
MAX_SHIFT = 8.0  # px, the centre's largest offset from the image centre
BORDER = 2.0  # px kept free of the shape on every side
PERIOD_DEG = {"arrows": 360.0, "bars": 180.0}  # the error is taken modulo the shape's symmetry
PAPER = {  # Table I, deg^2
    ("arrows", "Single Variable"): "237 ± 69", ("bars", "Single Variable"): "3597 ± 423",
    ("arrows", "One Hot (MSE)"): "112 ± 229", ("bars", "One Hot (MSE)"): "15.0 ± 1.7",
    ("arrows", "One Hot (Cross Entropy)"): "13.8 ± 1.2", ("bars", "One Hot (Cross Entropy)"): "12.6 ± 1.2",
    ("arrows", "Population Code"): "8.6 ± 0.5", ("bars", "Population Code"): "17.8 ± 2.3",
    ("bars", "Population Code (Sym)"): "8.7 ± 0.5",
}


def _rotated(points: np.ndarray, angle_rad: float, centre: np.ndarray) -> np.ndarray:
    """Shape points (x right, y up) rotated by ``angle_rad`` and placed at ``centre`` in pixel coordinates."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    x = points[:, 0] * c - points[:, 1] * s
    y = points[:, 0] * s + points[:, 1] * c
    return np.stack([centre[0] + x, centre[1] - y], axis=1)  # image y points down


def shape_polygons(kind: str, angle_rad: float, rng: np.random.Generator) -> list[np.ndarray]:
    """The filled polygons of one bar or arrow at ``angle_rad``, in pixel coordinates (see the module docstring)."""
    half_l, half_w = rng.uniform(16, 36) / 2, rng.uniform(3, 7) / 2
    polygons = [np.array([[-half_l, -half_w], [half_l, -half_w], [half_l, half_w], [-half_l, half_w]])]
    if kind == "arrows":
        head_l, head_w = rng.uniform(8, 12), half_w + rng.uniform(3, 6)
        polygons.append(np.array([[half_l + head_l, 0.0], [half_l, head_w], [half_l, -head_w]]))
    radius = max(np.linalg.norm(p, axis=1).max() for p in polygons)
    shift_limit = min(MAX_SHIFT, IMAGE_SIZE / 2 - BORDER - radius)  # the whole shape stays inside the image
    centre = IMAGE_SIZE / 2 + rng.uniform(-shift_limit, shift_limit, size=2)
    return [_rotated(p, angle_rad, centre) for p in polygons]


def draw_shape(kind: str, angle_rad: float, rng: np.random.Generator) -> np.ndarray:
    """One ``(64, 64)`` float32 image in [0, 1] of a bar or an arrow at ``angle_rad``, anti-aliased."""
    fraction_bits = 4  # sub-pixel vertices for cv2's fixed-point drawing
    image = np.zeros((IMAGE_SIZE, IMAGE_SIZE), np.uint8)
    polygons = [np.round(p * 2**fraction_bits).astype(np.int32) for p in shape_polygons(kind, angle_rad, rng)]
    cv2.fillPoly(image, polygons, 255, cv2.LINE_AA, fraction_bits)
    return image.astype(np.float32) / 255.0


def make_dataset(kind: str, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Images ``(count, 1, 64, 64)`` and their angles [rad] in [0, 2 pi)."""
    angles = rng.uniform(0.0, 2.0 * np.pi, size=count)
    images = np.stack([draw_shape(kind, a, rng) for a in angles])[:, None]
    return images, angles


def square_symmetry(images: np.ndarray, angles_rad: np.ndarray, quarter_turns: int,
                    mirror: bool) -> tuple[np.ndarray, np.ndarray]:
    """Images ``(N, 1, S, S)`` turned counter-clockwise by ``quarter_turns`` x 90 deg, then mirrored left-right if
    ``mirror``, and their angles [rad] in [0, 2 pi) (counter-clockwise from +x, y up: a mirror maps a to pi - a)."""
    turned = np.rot90(images, quarter_turns, axes=(2, 3))
    angles = angles_rad + quarter_turns * np.pi / 2.0
    if mirror:
        turned, angles = turned[..., ::-1], np.pi - angles
    return np.ascontiguousarray(turned), np.mod(angles, 2.0 * np.pi)
