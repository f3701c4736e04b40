"""Training samples: the runtime's crop of each instance, augmented, with its target.

Every sample draws from a generator seeded by ``(seed, epoch, index)``, so a sample is the same
whichever DataLoader worker makes it and in whatever order; call :meth:`CropDataset.set_epoch`
before each epoch (with ``persistent_workers=False``, the default, workers see the new epoch).

Crops are stored as uint8 with a margin for the shift augmentation (:mod:`.crop_cache`): decoded
once into a memory-mapped cache when a ``cache_dir`` is given (training), else from the images on
each access (a preview of a few crops). Every instance's target is made once, when the data set is
(a sample's target depends on its instance alone), or for a set too large for that, per DataLoader
batch in one vectorised call (``__getitems__``); the pixel arithmetic of a batch's crops is one too.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError

from .augment import Augmentation, AugmentationDraw, Backgrounds, occluder_alpha
from .bop import Instance
from .box_noise import BoxNoise, noisy_box
from .crop_cache import CropCache, crop_with_margin, margin_for_box_noise, margin_for_shift, window_affine

PAPER_AUGMENTATION = Augmentation()
# Background patches made per epoch and reused (with a random flip and quarter turn) by every crop:
# making one procedural texture costs more than the rest of a sample's augmentation.
BACKGROUNDS_PER_EPOCH = 256
# Gaussian noise fields of twice the crop side made per epoch; a crop's noise is a random window of one.
# Drawing fresh noise for every crop cost more than the rest of its augmentation (bench/results/training.md).
NOISE_FIELDS_PER_EPOCH = 8
BOX_NOISE_TRIES = 4  # draws of a detector-like box before the sample falls back to its true box
# A sample's target depends on its instance alone, so every instance's is made once, when the data set is, and kept
# up to this size (the quick recipe's 7200 crops of a 642 x 36 code: 0.67 GB); a larger set makes them per batch.
# Making them cost about a third of the data path of a step (bench/results/training.md).
TARGET_TABLE_BYTES = 1 << 30
TARGET_TABLE_CHUNK = 256  # instances per call of targets_fn while the table is made

TargetsFn = Callable[[Sequence[Instance]], np.ndarray]


def _require_mask(instance: Instance, augmentation: str) -> None:
    if instance.mask_visib_path is None:
        raise PopcodeError(f"{instance.image_path}: the {augmentation} augmentation needs its mask_visib image")


class CropDataset(Dataset):
    """Dicts ``image`` (1, S, S) in [0, 1], ``target``, ``R_m2c`` (3, 3), ``obj_id`` and ``index``.

    ``targets_fn`` maps a list of instances to their targets ``(B, D)``. ``background``: which rendered
    crops get a pasted background ("auto": single-object renders, not scenes, which keep their clutter;
    "always"; "never"). ``box_noise``: crops of detector-like boxes instead of the true ones (training), for a
    share ``box_noise_p`` of the crops (the rest from the true box).
    ``weights`` (one per instance): an epoch draws its crops with these relative chances (with
    replacement) instead of taking every crop once; ``index`` is then the instance drawn.
    """

    def __init__(self, instances: Sequence[Instance], targets_fn: TargetsFn,
                 augmentation: Augmentation | None = PAPER_AUGMENTATION,
                 backgrounds: Backgrounds | str | Path | None = None, crop_size: int = 128, seed: int = 0,
                 cache_dir: str | Path | None = None, progress: bool = False, background: str = "auto",
                 box_noise: BoxNoise | None = None, weights: Sequence[float] | None = None,
                 box_noise_p: float = 1.0) -> None:
        if len(instances) == 0:
            raise PopcodeError("no instances to make training samples from")
        if weights is not None and (len(weights) != len(instances) or not np.all(np.asarray(weights) > 0)):
            raise PopcodeError(f"need one positive sampling weight per instance ({len(instances)}), got "
                               f"{len(weights)} with minimum {np.min(weights) if len(weights) else 'none'}")
        self.instances = list(instances)
        self.targets_fn = targets_fn
        self.augmentation = augmentation
        self.backgrounds = backgrounds if isinstance(backgrounds, Backgrounds) else Backgrounds(backgrounds)
        self.background = background
        if not 0.0 < box_noise_p <= 1.0:  # NaN too
            raise PopcodeError(f"box_noise_p must lie in (0, 1], got {box_noise_p}")
        self.box_noise = None if box_noise is None or box_noise.is_none or augmentation is None else box_noise
        self.box_noise_p = box_noise_p
        self.crop_size = crop_size
        self.margin = margin_for_shift(augmentation.max_shift_crop_px) if augmentation else 0
        self.margin += margin_for_box_noise(crop_size) if self.box_noise else 0
        self.cache = None if cache_dir is None else CropCache(self.instances, crop_size, self.margin, cache_dir,
                                                              progress)
        self.weights = None if weights is None else np.asarray(weights, dtype=np.float64) / np.sum(weights)
        self.seed = seed
        self.epoch = 0
        self._bank: tuple[int, np.ndarray, np.ndarray] | None = None
        self._order: tuple[int, np.ndarray] | None = None
        self._targets = self._target_table(progress)

    def _target_table(self, progress: bool) -> np.ndarray | None:
        """Every instance's target ``(N, D)`` float32, made object by object; None where the table would pass
        :data:`TARGET_TABLE_BYTES` or the objects' targets differ in size (one model's data never do)."""
        obj_ids = np.array([int(instance.obj_id) for instance in self.instances])
        chunks = [rows[start : start + TARGET_TABLE_CHUNK] for obj_id in np.unique(obj_ids)
                  for rows in [np.flatnonzero(obj_ids == obj_id)] for start in range(0, len(rows), TARGET_TABLE_CHUNK)]
        table: np.ndarray | None = None
        for rows in tqdm(chunks, desc="making targets", unit="chunk", disable=not progress or len(chunks) < 2,
                         leave=False):
            part = np.asarray(self.targets_fn([self.instances[row] for row in rows]), dtype=np.float32)
            if table is None:
                if len(self.instances) * part[0].nbytes > TARGET_TABLE_BYTES:
                    return None
                table = np.empty((len(self.instances), *part.shape[1:]), np.float32)
            elif part.shape[1:] != table.shape[1:]:
                return None
            table[rows] = part
        return table

    def set_epoch(self, epoch: int) -> None:
        """Draw new augmentations: the generator of each sample is seeded by (seed, epoch, position in the epoch)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.instances)

    def instance_index(self, position: int) -> int:
        """The instance at ``position`` of this epoch: itself, or the weighted draw's."""
        if self.weights is None:
            return position
        if self._order is None or self._order[0] != self.epoch:
            rng = np.random.default_rng([self.seed, self.epoch, len(self.instances) + 1])
            self._order = (self.epoch, rng.choice(len(self.instances), size=len(self.instances), p=self.weights))
        return int(self._order[1][position])

    def pastes_background(self, instance: Instance) -> bool:
        if self.background == "never" or not instance.rendered:
            return False
        return self.background == "always" or not instance.cluttered

    def draw(self, position: int) -> tuple[AugmentationDraw | None, np.random.Generator]:
        """The augmentation a sample gets in this epoch, and the generator for its random content."""
        rng = np.random.default_rng([self.seed, self.epoch, position])
        if self.augmentation is None:
            return None, rng
        instance = self.instances[self.instance_index(position)]
        augment = self.augmentation.draw(rng, instance.rendered)
        if augment.background and not self.pastes_background(instance):
            augment = dataclasses.replace(augment, background=False)
        return augment, rng

    def _stored(self, index: int) -> tuple[np.ndarray, tuple[int, int]]:
        """The stored crop (:meth:`stored_crop`) and its image's (width, height), from one read."""
        if self.cache is not None:
            return self.cache[index], self.cache.image_size(index)
        return crop_with_margin(self.instances[index], self.crop_size, self.margin)

    def stored_crop(self, index: int) -> np.ndarray:
        """Image and visible mask ``(2, S + 2 margin, S + 2 margin)`` uint8 of one instance."""
        return self._stored(index)[0]

    def image_size(self, index: int) -> tuple[int, int]:
        return self._stored(index)[1]

    def _window(self, index: int, shift: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
        """The stored crop's ``(2, S, S)`` window: the true box shifted, or a detector-like box's crop."""
        size, (stored, image_size) = self.crop_size, self._stored(index)
        true_box = self.box_noise is None or (self.box_noise_p < 1.0 and rng.random() >= self.box_noise_p)
        if true_box:  # the shift (the paper's +-5 crop px), to the nearest pixel: a slice
            dx, dy = (int(round(v)) for v in shift)
            return stored[:, self.margin + dy : self.margin + dy + size, self.margin + dx : self.margin + dx + size]
        box = self.instances[index].box
        for _ in range(BOX_NOISE_TRIES):
            affine = window_affine(box, noisy_box(box, self.box_noise, rng, image_size), size, self.margin, shift)
            if affine is not None:
                break
        else:
            affine = window_affine(box, box, size, self.margin, shift)
        return np.stack([cv2.warpAffine(channel, affine, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
                         for channel in stored])

    def _banks(self) -> tuple[np.ndarray, np.ndarray]:
        """This epoch's background patches and noise fields, made once per epoch (and worker)."""
        if self._bank is None or self._bank[0] != self.epoch:
            bank_rng = np.random.default_rng([self.seed, self.epoch, len(self.instances)])
            count = min(BACKGROUNDS_PER_EPOCH, len(self.instances))
            patches = np.stack([self.backgrounds.sample(bank_rng, self.crop_size) for _ in range(count)])
            side = 2 * self.crop_size
            noise = bank_rng.standard_normal((NOISE_FIELDS_PER_EPOCH, side, side), dtype=np.float32)
            self._bank = (self.epoch, patches, noise)
        return self._bank[1], self._bank[2]

    def _background(self, rng: np.random.Generator) -> np.ndarray:
        patches = self._banks()[0]
        patch = patches[int(rng.integers(len(patches)))]
        patch = np.rot90(patch, int(rng.integers(4)))
        return patch[:, ::-1] if rng.random() < 0.5 else patch

    def _noise(self, rng: np.random.Generator) -> np.ndarray:
        """A unit Gaussian noise field ``(S, S)``: a random window of one of the epoch's fields, maybe flipped."""
        fields = self._banks()[1]
        y, x = rng.integers(0, self.crop_size + 1, size=2)
        window = fields[int(rng.integers(len(fields))), y : y + self.crop_size, x : x + self.crop_size]
        return window[::-1] if rng.random() < 0.5 else window

    def crop(self, position: int) -> np.ndarray:
        """The augmented crop ``(S, S)`` float32 in [0, 1] at ``position`` of the epoch."""
        return self.crops([position])[0]

    def crops(self, positions: Sequence[int]) -> np.ndarray:
        """The augmented crops ``(B, S, S)`` float32 in [0, 1] of a batch.

        Each sample's random choices come from its own generator, in a fixed order, so a crop does not
        depend on the batch it is in; the pixel arithmetic runs once over the batch.
        """
        size, count = self.crop_size, len(positions)
        windows = np.empty((count, 2, size, size), np.uint8)
        draws = []
        for row, position in enumerate(positions):
            augment, rng = self.draw(position)
            windows[row] = self._window(self.instance_index(position), augment.shift_crop_px if augment else (0, 0),
                                        rng)
            draws.append((augment, rng))
        crops = windows[:, 0].astype(np.float32) * np.float32(1.0 / 255.0)
        if self.augmentation is None:
            return crops
        alphas = windows[:, 1].astype(np.float32) * np.float32(1.0 / 255.0)
        for row, (augment, rng) in enumerate(draws):
            instance = self.instances[self.instance_index(positions[row])]
            crop, alpha = crops[row], alphas[row]
            crop += np.float32(augment.brightness)
            if augment.background:
                _require_mask(instance, "background")
                # Compositing the cropped mask as alpha equals pasting before the crop, with soft edges.
                crop += (1.0 - alpha) * (self._background(rng) - crop)
            if augment.occlusion:
                _require_mask(instance, "occlusion")
                occluder_mask = occluder_alpha(rng, alpha, self.augmentation.occlusion_max_fraction)
                occluder = self._background(rng) * rng.uniform(0.3, 1.0) + rng.uniform(0.0, 0.4)
                crop += occluder_mask * (occluder - crop)
            if augment.noise:
                crop += np.float32(self.augmentation.noise_sigma) * self._noise(rng)
        return np.clip(crops, 0.0, 1.0, out=crops)

    def _samples(self, positions: Sequence[int]) -> list[dict[str, Any]]:
        indices = [self.instance_index(position) for position in positions]
        targets = (self._targets[indices] if self._targets is not None
                   else self.targets_fn([self.instances[i] for i in indices]))
        crops = torch.from_numpy(self.crops(positions))
        return [{
            "image": crops[row][None],
            "target": torch.from_numpy(np.asarray(target, dtype=np.float32)),
            "R_m2c": torch.from_numpy(self.instances[index].R_m2c.astype(np.float32)),
            "obj_id": self.instances[index].obj_id,
            "index": index,
        } for row, (index, target) in enumerate(zip(indices, targets, strict=True))]

    def __getitem__(self, position: int) -> dict[str, Any]:
        return self._samples([position])[0]

    def __getitems__(self, positions: Sequence[int]) -> list[dict[str, Any]]:
        """A DataLoader batch: targets and crops each made in one vectorised call."""
        return self._samples(list(positions))
