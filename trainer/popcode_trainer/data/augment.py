"""The paper's training augmentation (section IV-D) and the backgrounds it pastes behind objects.

Rendered crops: brightness +-0.2 (p 0.5) and a background (p 0.7). All crops: Gaussian noise
sigma 0.02 (p 0.5) and a shift of up to +-5 crop pixels (p 0.9). What fires is drawn first
(:meth:`Augmentation.draw`), so the probabilities can be checked without images.

Not the paper's, off by default: an occluder (``occlusion_p``) pasted over part of a rendered
crop, so single-object renders teach what a cluttered bin shows (parts hiding parts); a scene
split (``popcode-train render --scenes``) has real occlusion instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.geometry.crop import read_image

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


@dataclass(frozen=True)
class AugmentationDraw:
    """What one sample gets; a value of 0 / False means that augmentation did not fire."""

    brightness: float  # added to every pixel
    background: bool
    noise: bool
    shift_crop_px: tuple[float, float]  # (dx, dy) in pixels of the output crop
    occlusion: bool = False


@dataclass(frozen=True)
class Augmentation:
    """Probabilities and strengths; defaults are the paper's."""

    brightness_delta: float = 0.2
    brightness_p: float = 0.5
    background_p: float = 0.7
    noise_sigma: float = 0.02
    noise_p: float = 0.5
    max_shift_crop_px: float = 5.0
    shift_p: float = 0.9
    occlusion_p: float = 0.0  # rendered crops: an occluder hides part of the object
    occlusion_max_fraction: float = 0.6  # of the object's visible pixels, at most (on average about half of it)

    def __post_init__(self) -> None:
        if not 0.0 <= self.occlusion_p <= 1.0 or not 0.0 < self.occlusion_max_fraction <= 1.0:
            raise PopcodeError(f"occlusion_p must lie in [0, 1] and occlusion_max_fraction in (0, 1], got "
                               f"{self.occlusion_p}, {self.occlusion_max_fraction}")
        if not 0.0 <= self.noise_sigma <= 1.0 or not 0.0 <= self.noise_p <= 1.0:
            raise PopcodeError(f"noise_sigma and noise_p must lie in [0, 1], got {self.noise_sigma} and {self.noise_p}")

    def draw(self, rng: np.random.Generator, rendered: bool) -> AugmentationDraw:
        """Decide what fires for one sample; brightness, background and occlusion only for rendered images."""
        fire = rng.random(4) < [self.brightness_p, self.background_p, self.noise_p, self.shift_p]
        brightness = rng.uniform(-self.brightness_delta, self.brightness_delta)
        shift = rng.uniform(-self.max_shift_crop_px, self.max_shift_crop_px, size=2)
        # Drawn only when switched on, so that the paper's augmentation draws exactly what it always drew.
        occlusion = self.occlusion_p > 0 and rng.random() < self.occlusion_p
        return AugmentationDraw(
            brightness=float(brightness) if rendered and fire[0] else 0.0,
            background=bool(rendered and fire[1]),
            noise=bool(fire[2]),
            shift_crop_px=(float(shift[0]), float(shift[1])) if fire[3] else (0.0, 0.0),
            occlusion=bool(rendered and occlusion),
        )


def procedural_texture(rng: np.random.Generator, size: int) -> np.ndarray:
    """A random clutter-like grey texture ``(size, size)`` in [0, 1]: smooth blobs, a gradient and strokes."""
    cells = int(rng.integers(2, 12))
    blobs = cv2.resize(rng.random((cells, cells)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
    ramp = np.linspace(0.0, 1.0, size, dtype=np.float32)
    angle = rng.uniform(0.0, 2.0 * np.pi)
    gradient = np.cos(angle) * ramp[None, :] + np.sin(angle) * ramp[:, None]
    texture = rng.uniform(0.3, 1.0) * blobs + rng.uniform(0.0, 0.5) * gradient
    for _ in range(int(rng.integers(0, 8))):
        start, end = rng.integers(0, size, size=(2, 2))
        thickness = int(rng.integers(1, max(2, size // 16)))
        cv2.line(texture, tuple(int(v) for v in start), tuple(int(v) for v in end),
                 float(rng.uniform(0.0, 1.5)), thickness)
    low, high = texture.min(), texture.max()
    contrast = rng.uniform(0.3, 1.0)
    return (texture - low) / max(high - low, 1e-6) * contrast + rng.uniform(0.0, 1.0 - contrast)


def occluder_alpha(rng: np.random.Generator, object_alpha: np.ndarray, max_fraction: float) -> np.ndarray:
    """Alpha ``(S, S)`` in [0, 1] of a random convex occluder over part of the object (``object_alpha`` > 0.5).

    A polygon of 3 to 8 corners grown from a point on the object's edge until it hides a random share
    of up to about ``max_fraction`` of the object's pixels: like a part lying across it.
    """
    size = object_alpha.shape[0]
    ys, xs = np.nonzero(object_alpha > 0.5)
    if len(xs) == 0:
        return np.zeros_like(object_alpha, dtype=np.float32)
    target = rng.uniform(0.1, max_fraction)
    centre = np.array([xs.mean(), ys.mean()])
    angle = rng.uniform(0.0, 2.0 * np.pi)
    direction = np.array([np.cos(angle), np.sin(angle)])
    reach = np.abs((np.stack([xs, ys], axis=1) - centre) @ direction).max()
    count = int(rng.integers(3, 9))
    # Corners spread around the middle (no gap of pi or more), so the polygon always contains it.
    corners = rng.uniform(0.0, 2.0 * np.pi) + (np.arange(count) + rng.uniform(-0.15, 0.15, count)) * 2.0 * np.pi / count
    radii = rng.uniform(0.6, 1.0, size=count)
    middle = centre + direction * reach  # on the object's edge: it grows over the object from one side
    alpha = np.zeros((size, size), np.float32)
    for scale in np.linspace(0.05, 1.5, 32) * size:  # grow the occluder until it hides enough
        points = middle + scale * radii[:, None] * np.stack([np.cos(corners), np.sin(corners)], axis=1)
        alpha[:] = 0.0
        cv2.fillConvexPoly(alpha, np.round(points * 16).astype(np.int32), 1.0, cv2.LINE_AA, shift=4)
        if (alpha[ys, xs] > 0.5).mean() >= target:
            break
    return alpha


class Backgrounds:
    """Background patches: random crops of the images in a folder, else procedural textures."""

    def __init__(self, folder: str | Path | None = None) -> None:
        self.paths: list[Path] = []
        if folder is not None:
            folder = Path(folder)
            if not folder.is_dir():
                raise PopcodeError(f"background folder not found: {folder}")
            self.paths = sorted(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self.paths:
                raise PopcodeError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in background folder {folder}")

    def sample(self, rng: np.random.Generator, size: int) -> np.ndarray:
        """One ``(size, size)`` float32 patch in [0, 1]."""
        if not self.paths:
            return np.clip(procedural_texture(rng, size), 0.0, 1.0).astype(np.float32)
        image = read_image(self.paths[int(rng.integers(len(self.paths)))])
        side = int(rng.integers(max(1, min(image.shape) // 4), min(image.shape) + 1))
        y0 = int(rng.integers(0, image.shape[0] - side + 1))
        x0 = int(rng.integers(0, image.shape[1] - side + 1))
        return cv2.resize(image[y0 : y0 + side, x0 : x0 + side], (size, size), interpolation=cv2.INTER_AREA)
