"""The detector box model: each preset's IoU, clipping to the image, seeding, and the exact ``none`` preset."""

from __future__ import annotations

import numpy as np
import pytest

from popcode_runtime.base.errors import PopcodeError
from popcode_trainer.data.box_noise import (
    BOX_NOISE_PRESETS,
    IOU_BINS,
    box_iou,
    box_noise_preset,
    iou_bin_label,
    iou_statistics,
    noisy_box,
)
from popcode_trainer.eval.pipeline.detector_boxes import detector_box, preset_name

IMAGE_WH = (160, 120)


@pytest.mark.parametrize(("name", "mean_iou"), [("tight", 0.9), ("detector", 0.75), ("loose", 0.6)])
def test_each_preset_gives_the_iou_it_is_named_for(name: str, mean_iou: float) -> None:
    stats = iou_statistics(box_noise_preset(name), draws=4000, seed=11)
    assert stats["mean"] == pytest.approx(mean_iou, abs=0.03)
    assert stats["p05"] < stats["median"] < stats["p95"] < 1.0  # a spread, not one fixed distortion


def test_the_none_preset_keeps_every_box_exactly() -> None:
    none = box_noise_preset("none")
    rng = np.random.default_rng(0)
    for box in [(10.0, 20.0, 31.0, 17.0), (0.0, 0.0, 160.0, 120.0), (33.5, 7.25, 12.75, 40.5)]:
        assert noisy_box(box, none, rng, IMAGE_WH) == box
        assert box_iou(box, noisy_box(box, none, rng)) == 1.0
    # A box the border cuts (bbox_obj runs past it) is kept as the split gives it: the ground-truth protocol.
    cut = (120.0, 90.0, 61.0, 57.0)
    assert detector_box(cut, none, 0, 1, 2, 3, IMAGE_WH) == cut
    assert iou_statistics(none)["mean"] == 1.0


@pytest.mark.parametrize("name", ["tight", "detector", "loose"])
def test_clipped_boxes_stay_inside_the_image(name: str) -> None:
    noise, (width, height) = box_noise_preset(name), IMAGE_WH
    rng = np.random.default_rng(4)
    boxes = [(-20.0, -10.0, 60.0, 50.0), (130.0, 95.0, 61.0, 57.0), (0.0, 0.0, 160.0, 120.0), (60.0, 40.0, 30.0, 30.0),
             (158.0, 50.0, 10.0, 10.0)]  # past the left and top, past the right and bottom, the whole image, ...
    for box in boxes:
        for _ in range(300):
            x, y, w, h = noisy_box(box, noise, rng, IMAGE_WH)
            assert x >= 0 and y >= 0 and x + w <= width + 1e-9 and y + h <= height + 1e-9, (box, (x, y, w, h))
            assert w >= 1.0 and h >= 1.0
    unclipped = [noisy_box((130.0, 95.0, 61.0, 57.0), noise, rng) for _ in range(50)]
    assert any(x + w > width for x, _, w, _ in unclipped)  # without the image size nothing is clipped


def test_one_seed_gives_each_instance_one_box() -> None:
    noise, box = box_noise_preset("detector"), (40.0, 30.0, 50.0, 40.0)
    first = detector_box(box, noise, 7, 1, 2, 3, IMAGE_WH)
    assert detector_box(box, noise, 7, 1, 2, 3, IMAGE_WH) == first
    others = [detector_box(box, noise, 8, 1, 2, 3, IMAGE_WH), detector_box(box, noise, 7, 1, 2, 4, IMAGE_WH),
              detector_box(box, noise, 7, 1, 3, 3, IMAGE_WH), detector_box(box, noise, 7, 2, 2, 3, IMAGE_WH)]
    assert all(other != first for other in others)  # seed, gt_index, image and scene each change the draw


def test_unknown_presets_are_named_with_the_known_ones() -> None:
    with pytest.raises(PopcodeError, match=r"unknown box-noise preset 'wild'; choose one of \['none', 'tight'"):
        box_noise_preset("wild")
    assert [preset_name(noise) for noise in BOX_NOISE_PRESETS.values()] == list(BOX_NOISE_PRESETS)


def test_iou_bins_cover_every_iou_once() -> None:
    for iou in np.linspace(0.0, 1.0, 101):
        assert sum(low <= iou < high for low, high in IOU_BINS) == 1
    assert iou_bin_label(*IOU_BINS[-1]) == "IoU 0.90-1.00"
