"""Training on scenes: a split mix by weight, scenes keep their clutter, crops of detector-like boxes."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from popcode_runtime import PopcodeError
from popcode_runtime.geometry.crop import crop_square, read_image
from popcode_trainer.data import crop_cache
from popcode_trainer.data.augment import Augmentation
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.box_noise import box_noise_preset, noisy_box
from popcode_trainer.data.crop_cache import CROP_PADDING, window_affine
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.data.samples import CropDataset
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.train.checkpoint import config_differences
from popcode_trainer.train.config import Config
from popcode_trainer.train.run_files import CROP_CACHE_FOLDER
from popcode_trainer.train.training_data import build_training_data, sampling_weights

PARTS = [3, 4, 5, 6]
ONLY_BACKGROUND = Augmentation(brightness_p=0.0, background_p=1.0, noise_p=0.0, shift_p=0.0)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return render_cluttered_test_split(tmp_path_factory.mktemp("scenes"), scenes=4, size=(160, 120), parts=(4, 6))


def _zeros(batch) -> np.ndarray:
    return np.zeros((len(batch), 1), np.float32)


def _config(splits: list[Path], models_dir: Path, out: Path, **data) -> Config:
    return Config.from_dict({
        "data": {"splits": [str(s) for s in splits], "models_dir": str(models_dir), "num_workers": 0,
                 "val_fraction": 0.0, "min_visib_fract": 0.3, "obj_ids": PARTS, **data},
        "code": {"n_axes": 42, "n_angles": 12, "sigma_deg": 30.0},
        "train": {"out_dir": str(out), "device": "cpu"},
    })


def test_scenes_keep_their_clutter_and_single_renders_get_a_background(scenes: Path, builtin_split: Path) -> None:
    scene_instances = read_bop_split(scenes, scenes / BUILTIN_MODELS_FOLDER, obj_ids=PARTS, min_visib_fract=0.3)
    single = read_bop_split(builtin_split, builtin_split / "models").instances[:4]
    assert all(inst.cluttered for inst in scene_instances.instances) and not any(inst.cluttered for inst in single)
    plain = dataclasses.replace(ONLY_BACKGROUND, background_p=0.0)
    for policy, scene_changes, single_changes in (("auto", False, True), ("always", True, True),
                                                  ("never", False, False)):
        for instances, changes in ((scene_instances.instances[:4], scene_changes), (single, single_changes)):
            with_background = CropDataset(instances, _zeros, augmentation=ONLY_BACKGROUND, background=policy)
            without = CropDataset(instances, _zeros, augmentation=plain)
            differs = [not np.array_equal(with_background.crop(i), without.crop(i)) for i in range(len(instances))]
            assert all(differs) if changes else not any(differs), (policy, instances[0].cluttered)


def test_split_weights_set_each_splits_share_of_an_epoch(scenes: Path, builtin_split: Path, tmp_path: Path) -> None:
    models_dir = scenes / BUILTIN_MODELS_FOLDER
    config = _config([builtin_split, scenes], models_dir, tmp_path / "run", split_weights=[1.0, 3.0],
                     noise_sigma=0.07, noise_p=0.9)
    data = build_training_data(config, progress=False)
    dataset = data.train_set
    assert (dataset.augmentation.noise_sigma, dataset.augmentation.noise_p) == (0.07, 0.9)  # the config's grain
    from_scenes = np.array([dataset.instances[dataset.instance_index(p)].cluttered for p in range(len(dataset))])
    n = len(dataset)
    assert abs(from_scenes.mean() - 0.75) <= 4 * np.sqrt(0.75 * 0.25 / n)
    first = [dataset.instance_index(p) for p in range(n)]
    dataset.set_epoch(1)
    assert [dataset.instance_index(p) for p in range(n)] != first
    dataset.set_epoch(0)
    assert [dataset.instance_index(p) for p in range(n)] == first
    sample = dataset[3]
    assert sample["index"] == first[3] and sample["obj_id"] == dataset.instances[first[3]].obj_id
    assert sampling_weights(dataset.instances, config.data.splits, ()) is None


@pytest.mark.parametrize("data, field", [
    ({"split_weights": [1.0, 0.0]}, "data.split_weights"),
    ({"split_weights": [1.0, -2.0]}, "data.split_weights"),
    ({"split_weights": [1.0]}, "data.split_weights"),
    ({"box_noise": "sloppy"}, "data.box_noise"),
    ({"box_noise": "detector", "box_noise_p": 0.0}, "data.box_noise_p"),
    ({"box_noise": "detector", "box_noise_p": 1.5}, "data.box_noise_p"),
    ({"background": "sometimes"}, "data.background"),
])
def test_bad_mix_settings_name_the_field(data: dict, field: str, tmp_path: Path) -> None:
    with pytest.raises(PopcodeError, match=field):
        _config([tmp_path / "a", tmp_path / "b"], tmp_path, tmp_path / "run", **data)


def test_an_exact_window_is_the_slice_of_the_stored_crop(builtin_split: Path) -> None:
    instance = read_bop_split(builtin_split, builtin_split / "models").instances[0]
    size, margin = 64, 20
    stored = crop_square(read_image(instance.image_path), instance.box, size + 2 * margin,
                         CROP_PADDING * (size + 2 * margin) / size)
    for dx, dy in ((0, 0), (3, -2)):
        affine = window_affine(instance.box, instance.box, size, margin, (dx, dy))
        warped = cv2.warpAffine(stored, affine, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        np.testing.assert_allclose(warped, stored[margin + dy: margin + dy + size, margin + dx: margin + dx + size],
                                   atol=1e-5)
    x, y, w, h = instance.box
    assert window_affine(instance.box, (x - 3 * w, y, w, h), size, margin) is None  # past the stored margin


def _best_alignment_error(a: np.ndarray, b: np.ndarray) -> float:
    """Mean difference of the inner parts after the best shift of up to one pixel (the runtime rounds its square
    to whole image pixels, the stored crop's window does not)."""
    inner = (slice(8, -8), slice(8, -8))
    return min(float(np.abs(np.roll(a, (dy, dx), axis=(0, 1))[inner] - b[inner]).mean())
               for dx in (-1, 0, 1) for dy in (-1, 0, 1))


def test_detector_like_boxes_crop_what_the_runtime_crops_of_them(builtin_split: Path) -> None:
    """A crop of a noisy box, taken from the stored crop of the true box, equals the runtime's crop of it."""
    instances = read_bop_split(builtin_split, builtin_split / "models").instances[:8]
    size, margin, noise = 128, 37, box_noise_preset("detector")
    checked = 0
    for index, instance in enumerate(instances):
        image = read_image(instance.image_path)
        stored = crop_square(image, instance.box, size + 2 * margin, CROP_PADDING * (size + 2 * margin) / size)
        box = noisy_box(instance.box, noise, np.random.default_rng(index), (image.shape[1], image.shape[0]))
        affine = window_affine(instance.box, box, size, margin)
        if affine is None:
            continue
        window = cv2.warpAffine(stored, affine, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
        assert _best_alignment_error(window, crop_square(image, box, size)) < 0.012, index
        checked += 1
    assert checked >= 5

    only_box_noise = Augmentation(brightness_p=0.0, background_p=0.0, noise_p=0.0, shift_p=0.0)
    noisy = CropDataset(instances, _zeros, augmentation=only_box_noise, box_noise=noise)
    exact = CropDataset(instances, _zeros, augmentation=only_box_noise)
    assert noisy.margin > exact.margin
    assert sum(not np.allclose(noisy.crop(i), exact.crop(i), atol=0.05) for i in range(len(instances))) >= 6
    assert all(np.array_equal(noisy.crop(i), noisy.crop(i)) for i in range(3))  # seeded per sample


def test_a_share_of_the_crops_comes_from_noisy_boxes_the_rest_from_the_true_one(builtin_split: Path) -> None:
    instances = read_bop_split(builtin_split, builtin_split / "models").instances[:8]
    only_box_noise = Augmentation(brightness_p=0.0, background_p=0.0, noise_p=0.0, shift_p=0.0)
    exact = CropDataset(instances, _zeros, augmentation=only_box_noise)
    half = CropDataset(instances, _zeros, augmentation=only_box_noise, box_noise=box_noise_preset("detector"),
                       box_noise_p=0.5)
    true_boxes = [np.array_equal(half.crop(i), exact.crop(i)) for i in range(len(instances))]
    assert 0 < sum(true_boxes) < len(instances)  # some crops of the true box, some of a noisy one
    with pytest.raises(PopcodeError, match="box_noise_p"):
        CropDataset(instances, _zeros, augmentation=only_box_noise, box_noise_p=float("nan"))


def test_the_cache_of_a_scene_split_built_by_threads_equals_crops_made_one_by_one(
        scenes: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Threads fill runs of the cache side by side, each reading a scene's image once for its instances."""
    instances = read_bop_split(scenes, scenes / BUILTIN_MODELS_FOLDER, obj_ids=PARTS, min_visib_fract=0.1).instances
    images = {inst.image_path for inst in instances}
    assert len(instances) > len(images) > 1  # several instances share each scene's image
    reads: list[Path] = []
    monkeypatch.setattr(crop_cache, "read_image", lambda path: reads.append(Path(path)) or read_image(path))
    monkeypatch.setattr(crop_cache, "CACHE_THREADS", 3)
    monkeypatch.setattr(crop_cache, "CHUNKS_PER_THREAD", 1)
    cache = crop_cache.CropCache(instances, 32, 4, tmp_path, progress=False)
    image_reads = [path for path in reads if path in images]
    assert len(image_reads) < len(instances)  # an image is not read again for the next instance of its scene
    for index, instance in enumerate(instances):
        crops, size = crop_cache.crop_with_margin(instance, 32, 4)
        assert np.array_equal(cache[index], crops) and cache.image_size(index) == size


def test_runs_that_name_one_cache_dir_decode_their_crops_once(scenes: Path, builtin_split: Path,
                                                              tmp_path: Path) -> None:
    """The demo's models of a group share a cache; a resume may move it (it is named by what it holds)."""
    shared = tmp_path / "shared_cache"
    first = _config([builtin_split, scenes], scenes / BUILTIN_MODELS_FOLDER, tmp_path / "a", cache_dir=str(shared))
    build_training_data(first, progress=False)
    cached = sorted(shared.glob("*.crops.npy"))
    built = [path.stat().st_mtime_ns for path in cached]
    assert cached and not (tmp_path / "a" / CROP_CACHE_FOLDER).exists()
    second = dataclasses.replace(first, train=dataclasses.replace(first.train, out_dir=str(tmp_path / "b")))
    build_training_data(second, progress=False)
    assert sorted(shared.glob("*.crops.npy")) == cached and [p.stat().st_mtime_ns for p in cached] == built
    assert not (tmp_path / "b").exists()
    default = dataclasses.replace(first, data=dataclasses.replace(first.data, cache_dir=""))
    build_training_data(default, progress=False)
    assert sorted(p.name for p in (tmp_path / "a" / CROP_CACHE_FOLDER).glob("*.crops.npy")) == [p.name for p in cached]
    assert config_differences(first.to_dict(), default.to_dict(), Config().to_dict()) == []
