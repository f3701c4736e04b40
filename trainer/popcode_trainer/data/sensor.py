"""What a real camera does to an image: exposure, blur, noise, gamma, grey conversion and JPEG compression.

Applied by the renderer to the whole rendered frame, not by the training augmentation to a crop:
blur, noise and JPEG blocks act on camera pixels, and a crop is resized from boxes of any size,
so the same effect applied to crops would mean a different camera for every part size. A rendered
test split with sensor effects then also resembles what the camera delivers at run time.

The chain follows a camera's: light (linear) -> optics (defocus, motion blur) -> exposure ->
sensor (shot noise grows with the signal, read noise does not) -> grey conversion of a mono
sensor (spectral weights vary between sensors) -> gamma -> 8 bits -> JPEG. Every strength is
drawn per image, uniformly from its range; a probability of 0 switches that effect off.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from popcode_runtime.base.errors import PopcodeError

DISPLAY_GAMMA = 2.2  # the rendered colours are taken as display values with this gamma


@dataclass(frozen=True)
class SensorEffects:
    """Ranges ``(low, high)`` drawn per image; ``*_p`` the probability that an effect fires."""

    exposure_stops: tuple[float, float] = (0.0, 0.0)  # brightness x 2**stops
    defocus_sigma_px: tuple[float, float] = (0.0, 0.0)  # Gaussian blur of the optics
    defocus_p: float = 0.0
    motion_blur_px: tuple[float, float] = (0.0, 0.0)  # length of a straight motion streak, any direction
    motion_blur_p: float = 0.0
    full_well_electrons: tuple[float, float] = (0.0, 0.0)  # electrons at white: shot noise; 0 = none
    read_noise: tuple[float, float] = (0.0, 0.0)  # Gaussian sigma, fraction of white
    grey_weight_jitter: float = 0.0  # mono sensors weigh R, G, B differently from BT.601
    gamma: tuple[float, float] = (1.0, 1.0)  # encoding gamma relative to the display's
    jpeg_quality: tuple[int, int] = (100, 100)
    jpeg_p: float = 0.0

    def __post_init__(self) -> None:
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            values = value if isinstance(value, tuple) else (value,)
            if any(not np.isfinite(v) or v < 0 for v in values) and field.name != "exposure_stops":
                raise PopcodeError(f"sensor effect {field.name} must be non-negative, got {value}")
            if isinstance(value, tuple) and value[0] > value[1]:
                raise PopcodeError(f"sensor effect {field.name}: low {value[0]} above high {value[1]}")
            if field.name.endswith("_p") and value > 1:
                raise PopcodeError(f"sensor effect {field.name} is a probability, got {value}")
        if self.gamma[0] <= 0 or not 1 <= self.jpeg_quality[0] <= self.jpeg_quality[1] <= 100:
            raise PopcodeError(f"sensor effects need gamma > 0 and 1 <= JPEG quality <= 100, got {self}")


# Presets named after the camera they resemble; README "Rendering training data for your own parts".
SENSOR_PRESETS: dict[str, SensorEffects | None] = {
    "none": None,
    # A machine-vision camera (mono, global shutter, good lens, raw 8-bit): a little noise and focus error.
    "industrial": SensorEffects(exposure_stops=(-0.5, 0.5), defocus_sigma_px=(0.3, 1.0), defocus_p=0.3,
                                full_well_electrons=(2000.0, 10000.0), read_noise=(0.002, 0.008),
                                grey_weight_jitter=0.15, gamma=(0.9, 1.1)),
    # A depth camera's colour/IR stream or a webcam (T-LESS Primesense-like): noisy, soft, compressed.
    "webcam": SensorEffects(exposure_stops=(-1.0, 1.0), defocus_sigma_px=(0.5, 1.5), defocus_p=0.5,
                            motion_blur_px=(1.0, 5.0), motion_blur_p=0.3, full_well_electrons=(300.0, 2000.0),
                            read_noise=(0.005, 0.02), grey_weight_jitter=0.1, gamma=(0.8, 1.25),
                            jpeg_quality=(60, 95), jpeg_p=0.7),
    # A phone: strong denoising and sharpening leave little noise but heavy compression and exposure swings.
    "phone": SensorEffects(exposure_stops=(-1.0, 1.0), defocus_sigma_px=(0.3, 1.2), defocus_p=0.3,
                           motion_blur_px=(1.0, 4.0), motion_blur_p=0.2, full_well_electrons=(3000.0, 20000.0),
                           read_noise=(0.001, 0.005), gamma=(0.85, 1.2), jpeg_quality=(50, 90), jpeg_p=1.0),
}


def sensor_preset(name: str) -> SensorEffects | None:
    if name not in SENSOR_PRESETS:
        raise PopcodeError(f"unknown sensor preset {name!r}; choose one of {sorted(SENSOR_PRESETS)}")
    return SENSOR_PRESETS[name]


def _motion_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    size = int(np.ceil(length_px)) | 1
    kernel = np.zeros((size, size), np.float32)
    centre = size // 2
    offset = 0.5 * (length_px - 1) * np.array([np.cos(angle_rad), np.sin(angle_rad)])
    start, end = np.round(centre - offset).astype(int), np.round(centre + offset).astype(int)
    cv2.line(kernel, (int(start[0]), int(start[1])), (int(end[0]), int(end[1])), 1.0, 1)
    return kernel / kernel.sum()


def apply_sensor_effects(rgb: np.ndarray, rng: np.random.Generator, effects: SensorEffects,
                         gray: bool) -> np.ndarray:
    """A rendered ``(H, W, 3)`` uint8 frame as the camera would deliver it: uint8 ``(H, W)`` if ``gray``."""
    linear = (rgb.astype(np.float32) / 255.0) ** DISPLAY_GAMMA
    if rng.random() < effects.defocus_p:
        linear = cv2.GaussianBlur(linear, (0, 0), max(float(rng.uniform(*effects.defocus_sigma_px)), 1e-3))
    if rng.random() < effects.motion_blur_p:
        kernel = _motion_kernel(rng.uniform(*effects.motion_blur_px), rng.uniform(0.0, np.pi))
        linear = cv2.filter2D(linear, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if gray:
        weights = np.array([0.299, 0.587, 0.114]) * np.exp(effects.grey_weight_jitter * rng.standard_normal(3))
        linear = linear @ (weights / weights.sum()).astype(np.float32)
    linear = linear * np.float32(2.0 ** rng.uniform(*effects.exposure_stops))
    full_well = rng.uniform(*effects.full_well_electrons)
    if full_well > 0:
        electrons = rng.poisson(np.clip(linear, 0.0, 1.0) * full_well)
        linear = (electrons / full_well).astype(np.float32)
    read_sigma = rng.uniform(*effects.read_noise)
    if read_sigma > 0:
        linear = linear + np.float32(read_sigma) * rng.standard_normal(linear.shape, dtype=np.float32)
    encoded = np.clip(linear, 0.0, 1.0) ** np.float32(1.0 / (DISPLAY_GAMMA * rng.uniform(*effects.gamma)))
    image = np.round(encoded * 255.0).astype(np.uint8)
    if rng.random() < effects.jpeg_p:
        quality = int(rng.integers(effects.jpeg_quality[0], effects.jpeg_quality[1] + 1))
        ok, data = cv2.imencode(".jpg", image if gray else image[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise PopcodeError("cannot JPEG-encode a rendered image")
        decoded = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
        image = decoded if gray else decoded[..., ::-1]
    return image
