"""Training samples: augmentation fires at its probabilities, crops are deterministic and worker-safe."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from popcode_runtime import CodeLayout, PopcodeError, read_image
from popcode_runtime.geometry.crop import crop_square
from popcode_trainer.cli import main
from popcode_trainer.data import samples
from popcode_trainer.data.augment import Augmentation, Backgrounds, procedural_texture
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.crop_cache import CACHE_SUFFIX, crop_with_margin
from popcode_trainer.data.samples import CropDataset
from popcode_trainer.train.representations import PerObjectPopulationCodes

DRAWS = 2000
SMALL_CODE = CodeLayout(n_axes=162, n_angles=12)


def _within_binomial(count: int, p: float, n: int = DRAWS) -> bool:
    return abs(count - n * p) <= 4.0 * np.sqrt(n * p * (1.0 - p)) + 1e-9


@pytest.mark.parametrize("rendered", [True, False])
def test_each_augmentation_fires_at_its_probability(rendered: bool) -> None:
    augmentation = Augmentation()
    draws = [augmentation.draw(np.random.default_rng([5, index]), rendered) for index in range(DRAWS)]
    brightness = np.array([draw.brightness for draw in draws])
    shifts = np.array([draw.shift_crop_px for draw in draws])
    fired = {
        "brightness": (int((brightness != 0).sum()), 0.5 if rendered else 0.0),
        "background": (sum(draw.background for draw in draws), 0.7 if rendered else 0.0),
        "noise": (sum(draw.noise for draw in draws), 0.5),
        "shift": (int(np.any(shifts != 0, axis=1).sum()), 0.9),
    }
    for name, (count, p) in fired.items():
        assert _within_binomial(count, p), f"{name} fired {count} of {DRAWS} times, expected p={p}"
    assert np.abs(brightness).max() <= 0.2 and np.abs(shifts).max() <= 5.0
    if rendered:  # uniform +-0.2: mean near 0, spread near 0.2 / sqrt 3
        assert abs(brightness[brightness != 0].mean()) < 0.02
        assert brightness[brightness != 0].std() == pytest.approx(0.2 / np.sqrt(3), rel=0.1)


@pytest.fixture(scope="module")
def split(builtin_split: Path):
    return read_bop_split(builtin_split, builtin_split / "models")


def _codes(split) -> PerObjectPopulationCodes:
    return PerObjectPopulationCodes(split.models_info, SMALL_CODE.n_axes, SMALL_CODE.n_angles, SMALL_CODE.sigma_deg)


def _dataset(split, **kwargs) -> CropDataset:
    return CropDataset(split.instances, _codes(split).targets, **kwargs)


def _dataset_of(instances, **kwargs) -> CropDataset:
    return CropDataset(instances, lambda batch: np.zeros((len(batch), 1)), **kwargs)


def test_sample_contents_and_targets(split) -> None:
    dataset = _dataset(split, augmentation=None)
    for index in (0, len(dataset) - 1):
        sample = dataset[index]
        instance = split.instances[index]
        assert sample["image"].shape == (1, 128, 128) and sample["image"].dtype == torch.float32
        expected = crop_square(read_image(instance.image_path), instance.box)
        # The runtime's crop, stored to 8 bits like the PNG it comes from.
        np.testing.assert_allclose(sample["image"][0].numpy(), expected, atol=0.5 / 255 + 1e-6)
        np.testing.assert_array_equal(sample["R_m2c"].numpy(), instance.R_m2c.astype(np.float32))
        assert sample["obj_id"] == instance.obj_id and sample["index"] == index
    sizes = {instance.obj_id: dataset[index]["target"].numel() for index, instance in enumerate(split.instances)}
    assert sizes[1] == sizes[2] == SMALL_CODE.n_axes  # continuous symmetry: axis-only code
    assert sizes[3] == sizes[6] == SMALL_CODE.n_axes * SMALL_CODE.n_angles
    codes = _codes(split)
    assert codes.layout(1).axis_only and not codes.layout(3).axis_only
    assert all(codes.layout(obj_id).size == size for obj_id, size in sizes.items())


def test_targets_are_made_once_and_equal_those_made_per_batch(split, monkeypatch) -> None:
    one_size = [instance for instance in split.instances if instance.obj_id >= 3]  # the full code: one length
    calls = []

    def counted(instances):
        calls.append(len(instances))
        return _codes(split).targets(instances)

    tabled = CropDataset(one_size, counted, augmentation=None)
    assert sum(calls) == len(one_size)  # every instance once, when the data set is made
    positions = [5, 0, 3, 3]
    from_table = tabled.__getitems__(positions)
    assert sum(calls) == len(one_size)
    monkeypatch.setattr(samples, "TARGET_TABLE_BYTES", 0)
    per_batch = CropDataset(one_size, counted, augmentation=None).__getitems__(positions)
    assert calls[-1] == len(positions)  # too large for the table: made for each batch
    for tabled_sample, batch_sample in zip(from_table, per_batch, strict=True):
        assert torch.equal(tabled_sample["target"], batch_sample["target"])
    mixed = CropDataset(split.instances, counted, augmentation=None)  # axis-only and full codes: no one table
    assert mixed[0]["target"].numel() != mixed[len(mixed) - 1]["target"].numel()


def test_augmented_samples_are_deterministic_per_seed_epoch_and_index(split) -> None:
    dataset = _dataset(split)
    first = [dataset[index]["image"] for index in range(6)]
    again = _dataset(split)
    assert all(torch.equal(a, again[index]["image"]) for index, a in enumerate(first))
    assert all(float(image.min()) >= 0.0 and float(image.max()) <= 1.0 for image in first)
    again.set_epoch(1)
    assert not all(torch.equal(a, again[index]["image"]) for index, a in enumerate(first))
    loader = DataLoader(dataset, batch_size=3, num_workers=2, shuffle=False)
    batched = torch.cat([batch["image"] for _, batch in zip(range(2), loader, strict=False)])
    assert torch.equal(batched, torch.stack(first))


def test_background_replaces_only_pixels_off_the_object(split) -> None:
    only_background = Augmentation(brightness_p=0.0, background_p=1.0, noise_p=0.0, shift_p=0.0)
    nothing = dataclasses.replace(only_background, background_p=0.0)
    plain, augmented = _dataset(split, augmentation=nothing), _dataset(split, augmentation=only_background)
    inner = slice(augmented.margin, augmented.margin + augmented.crop_size)
    for index in range(0, len(split.instances), 4):
        alpha = augmented.stored_crop(index)[1, inner, inner] / 255.0
        before, after = plain.crop(index), augmented.crop(index)
        np.testing.assert_allclose(after[alpha == 1.0], before[alpha == 1.0], atol=1e-6)
        assert np.abs(after[alpha == 0.0] - before[alpha == 0.0]).mean() > 0.05
    real = [dataclasses.replace(instance, rendered=False) for instance in split.instances[:3]]
    real_plain = CropDataset(real, lambda batch: np.zeros((len(batch), 1)), augmentation=nothing)
    real_augmented = CropDataset(real, lambda batch: np.zeros((len(batch), 1)), augmentation=only_background)
    for index in range(3):  # real images never get a background
        np.testing.assert_array_equal(real_plain.crop(index), real_augmented.crop(index))


def test_backgrounds_from_a_folder_and_procedural(tmp_path: Path) -> None:
    cv2.imwrite(str(tmp_path / "wall.png"), np.random.default_rng(0).integers(0, 255, (90, 200), dtype=np.uint8))
    patch = Backgrounds(tmp_path).sample(np.random.default_rng(1), 128)
    assert patch.shape == (128, 128) and patch.min() >= 0.0 and patch.max() <= 1.0
    textures = [procedural_texture(np.random.default_rng(seed), 64) for seed in range(5)]
    assert all(texture.min() >= 0.0 and texture.max() <= 1.0 and texture.std() > 0.01 for texture in textures)
    assert not np.allclose(textures[0], textures[1])
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(PopcodeError, match="no images"):
        Backgrounds(empty)


def test_render_and_preview_commands(tmp_path: Path) -> None:
    out = tmp_path / "split"
    assert main(["render", "--objects", "builtin", "--out", str(out), "--images", "2", "--obj-ids", "2", "4",
                 "--size", "96", "80", "--quiet"]) == 0
    assert len(read_bop_split(out, out / "models").instances) == 4
    assert main(["preview", "--split", str(out), "--out", str(tmp_path / "grid.png"), "--count", "4"]) == 0
    assert cv2.imread(str(tmp_path / "grid.png")).shape[2] == 3
    assert main(["render", "--objects", str(tmp_path / "nowhere"), "--out", str(out), "--images", "1"]) == 2
    assert main(["render", "--objects", "builtin", "--out", str(out), "--images", "2", "--shard", "2/2"]) == 2


def test_stored_crops_centre_on_the_runtime_crop(split) -> None:
    """The stored crop's inner square is the runtime crop: no window one pixel off matches it better."""
    margin, size = 5, 128
    offsets = [(dy, dx) for dy in range(-2, 3) for dx in range(-2, 3)]
    error = dict.fromkeys(offsets, 0.0)
    for instance in split.instances:
        stored = crop_with_margin(instance, size, margin)[0][0] / 255.0
        runtime = crop_square(read_image(instance.image_path), instance.box, size)
        for dy, dx in offsets:
            window = stored[margin + dy: margin + dy + size, margin + dx: margin + dx + size]
            error[dy, dx] += np.abs(window - runtime).mean() / len(split.instances)
    assert min(error, key=error.get) == (0, 0), error
    assert error[0, 0] < 0.02  # resampling differs by under half a source pixel


def test_cached_crops_equal_decoded_ones_and_follow_the_images(split, tmp_path: Path) -> None:
    instances = [dataclasses.replace(inst, image_path=tmp_path / inst.image_path.name) for inst in split.instances[:4]]
    for original, copy in zip(split.instances, instances, strict=False):
        copy.image_path.write_bytes(original.image_path.read_bytes())
    cache_dir = tmp_path / "cache"
    cached = _dataset_of(instances, cache_dir=cache_dir)
    decoded = _dataset_of(instances)
    for index in range(len(instances)):
        assert torch.equal(cached[index]["image"], decoded[index]["image"])
    first = sorted(cache_dir.glob(f"*{CACHE_SUFFIX}"))
    assert len(first) == 1 and len(list(cache_dir.iterdir())) == 2  # the crops and their images' sizes
    assert cached.image_size(0) == decoded.image_size(0) == (128, 128)
    built = first[0].stat().st_mtime_ns
    _dataset_of(instances, cache_dir=cache_dir)  # the same data: reused, not rebuilt
    assert sorted(cache_dir.glob(f"*{CACHE_SUFFIX}")) == first and first[0].stat().st_mtime_ns == built
    # A changed image makes a new cache with the new pixels.
    flipped = cv2.imread(str(instances[0].image_path), cv2.IMREAD_UNCHANGED)[::-1]
    cv2.imwrite(str(instances[0].image_path), flipped)
    os.utime(instances[0].image_path, ns=(built + 10**9, built + 10**9))
    changed = _dataset_of(instances, cache_dir=cache_dir)
    assert len(list(cache_dir.glob(f"*{CACHE_SUFFIX}"))) == 2
    assert torch.equal(changed[0]["image"], _dataset_of(instances)[0]["image"])
    assert not torch.equal(changed[0]["image"], cached[0]["image"])
    loader = DataLoader(changed, batch_size=2, num_workers=2, shuffle=False)
    assert torch.equal(torch.cat([batch["image"] for batch in loader]),
                       torch.stack([changed[index]["image"] for index in range(len(instances))]))


def test_an_interrupted_cache_build_leaves_no_file(split, tmp_path: Path) -> None:
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png")
    with pytest.raises(PopcodeError, match="cannot read image"):
        _dataset_of([split.instances[0], dataclasses.replace(split.instances[1], image_path=broken)],
                    cache_dir=tmp_path / "cache")
    assert list((tmp_path / "cache").iterdir()) == []
    with pytest.raises(PopcodeError, match="image file not found"):
        _dataset_of([dataclasses.replace(split.instances[1], image_path=tmp_path / "gone.png")],
                    cache_dir=tmp_path / "cache")



def test_occlusion_is_off_by_default_and_hides_part_of_the_object_when_on(split) -> None:
    rng_draws = [Augmentation().draw(np.random.default_rng([5, i]), True) for i in range(50)]
    assert not any(draw.occlusion for draw in rng_draws)
    on = Augmentation(occlusion_p=0.5)
    draws = [on.draw(np.random.default_rng([5, i]), True) for i in range(DRAWS)]
    assert _within_binomial(sum(draw.occlusion for draw in draws), 0.5)
    # Switching occlusion on leaves every other draw as it was: the paper's augmentation is unchanged.
    assert [dataclasses.replace(d, occlusion=False) for d in draws[:50]] == rng_draws
    assert not any(on.draw(np.random.default_rng([5, i]), False).occlusion for i in range(50))
    only_occlusion = Augmentation(brightness_p=0.0, background_p=0.0, noise_p=0.0, shift_p=0.0, occlusion_p=1.0,
                                  occlusion_max_fraction=0.6)
    plain = _dataset(split, augmentation=dataclasses.replace(only_occlusion, occlusion_p=0.0))
    occluded = _dataset(split, augmentation=only_occlusion)
    inner = slice(occluded.margin, occluded.margin + occluded.crop_size)
    for index in range(0, len(split.instances), 3):
        on_object = occluded.stored_crop(index)[1, inner, inner] == 255
        changed = np.abs(occluded.crop(index) - plain.crop(index)) > 1e-6
        hidden = changed[on_object].mean()
        assert 0.0 < hidden < 0.9, f"instance {index}: {hidden:.2f} of the object hidden"
    with pytest.raises(PopcodeError, match="occlusion_p"):
        Augmentation(occlusion_p=1.5)


@pytest.mark.parametrize("settings", [{"noise_sigma": -0.1}, {"noise_sigma": float("nan")}, {"noise_p": 1.5}])
def test_grain_out_of_range_is_refused(settings: dict) -> None:
    with pytest.raises(PopcodeError, match="noise_sigma and noise_p must lie in"):
        Augmentation(**settings)


def test_noise_is_gaussian_with_the_configured_sigma_and_differs_per_crop(split) -> None:
    only_noise = Augmentation(brightness_p=0.0, background_p=0.0, noise_p=1.0, noise_sigma=0.05, shift_p=0.0)
    nothing = dataclasses.replace(only_noise, noise_p=0.0)
    plain, noisy = _dataset(split, augmentation=nothing), _dataset(split, augmentation=only_noise)
    indices = list(range(min(8, len(split.instances))))
    before, after = plain.crops(indices), noisy.crops(indices)
    inside = (before > 0.2) & (before < 0.8)  # away from the clip at 0 and 1
    noise = (after - before)[inside]
    assert abs(float(noise.mean())) < 0.005
    assert abs(float(noise.std()) - 0.05) < 0.005
    assert not np.allclose(after[0] - before[0], after[1] - before[1])
