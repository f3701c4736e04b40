"""Sensor effects: off means the plain image, each effect does what its name says, bad ranges are refused."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from popcode_runtime import PopcodeError
from popcode_trainer.data.sensor import SENSOR_PRESETS, SensorEffects, apply_sensor_effects, sensor_preset


def _frame() -> np.ndarray:
    """A grey ramp with a sharp bright square: noise, blur and gain all show on it."""
    ramp = np.tile(np.linspace(40, 200, 96, dtype=np.float32), (64, 1))
    ramp[20:40, 30:50] = 230
    return np.repeat(ramp[..., None], 3, axis=2).round().astype(np.uint8)


def test_no_effect_leaves_the_image_as_rendered() -> None:
    frame = _frame()
    rgb = apply_sensor_effects(frame, np.random.default_rng(0), SensorEffects(), gray=False)
    gray = apply_sensor_effects(frame, np.random.default_rng(0), SensorEffects(), gray=True)
    assert np.abs(rgb.astype(int) - frame).max() <= 1
    assert gray.shape == frame.shape[:2]
    assert np.abs(gray.astype(int) - cv2.cvtColor(frame, cv2.COLOR_RGB2GRAY)).max() <= 1


def test_each_effect_changes_the_image_as_named() -> None:
    frame, rng = _frame(), np.random.default_rng(1)
    plain = apply_sensor_effects(frame, rng, SensorEffects(), gray=True).astype(float)
    brighter = apply_sensor_effects(frame, rng, SensorEffects(exposure_stops=(1.0, 1.0)), gray=True).astype(float)
    assert brighter[:, :20].mean() > plain[:, :20].mean() + 20
    noisy = apply_sensor_effects(frame, rng, SensorEffects(full_well_electrons=(100.0, 100.0)), gray=True)
    assert np.std(noisy.astype(float)[:, :10] - plain[:, :10]) > 3
    blurred = apply_sensor_effects(frame, rng, SensorEffects(defocus_sigma_px=(2.0, 2.0), defocus_p=1.0), gray=True)
    edge = slice(28, 32)  # the square's left edge: blur spreads it
    assert np.abs(np.diff(blurred[25:35, edge].astype(float), axis=1)).max() < \
        np.abs(np.diff(plain[25:35, edge], axis=1)).max()
    streaked = apply_sensor_effects(frame, rng, SensorEffects(motion_blur_px=(7.0, 7.0), motion_blur_p=1.0),
                                    gray=True)
    assert not np.array_equal(streaked, plain.astype(np.uint8))
    jpeg = apply_sensor_effects(frame, rng, SensorEffects(jpeg_quality=(5, 5), jpeg_p=1.0), gray=True)
    assert np.abs(jpeg.astype(float) - plain).mean() > 0


def test_presets_and_bad_ranges() -> None:
    assert sensor_preset("none") is None
    for name in SENSOR_PRESETS:
        effects = sensor_preset(name)
        if effects is not None:
            image = apply_sensor_effects(_frame(), np.random.default_rng(2), effects, gray=True)
            assert image.dtype == np.uint8 and image.shape == (64, 96)
    with pytest.raises(PopcodeError, match="unknown sensor preset"):
        sensor_preset("fisheye")
    for bad in ({"defocus_p": 1.5}, {"read_noise": (0.1, 0.0)}, {"full_well_electrons": (-1.0, 1.0)},
                {"jpeg_quality": (0, 50)}, {"gamma": (0.0, 1.0)}):
        with pytest.raises(PopcodeError):
            SensorEffects(**bad)
