"""Training samples: the runtime's crop of each instance, augmented, with its target.

Every sample draws from a generator seeded by ``(seed, epoch, index)``, so a sample is the same
whichever DataLoader worker makes it and in whatever order; call :meth:`CropDataset.set_epoch`
before each epoch (with ``persistent_workers=False``, the default, workers see the new epoch).

Crops are stored as uint8 with a margin for the shift augmentation (:mod:`.crop_cache`): decoded
once into a memory-mapped cache when a ``cache_dir`` is given (training), else from the images on
each access (a preview of a few crops). Targets of a DataLoader batch are built in one vectorised
call (``__getitems__``), not one crop at a time.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from popcode_runtime.errors import PopcodeError

from .augment import Augmentation, AugmentationDraw, Backgrounds, occluder_alpha
from .bop import Instance
from .crop_cache import CropCache, crop_with_margin, margin_for_shift

PAPER_AUGMENTATION = Augmentation()
# Background patches made per epoch and reused (with a random flip and quarter turn) by every crop:
# making one procedural texture costs more than the rest of a sample's augmentation.
BACKGROUNDS_PER_EPOCH = 256

TargetsFn = Callable[[Sequence[Instance]], np.ndarray]


def _require_mask(instance: Instance, augmentation: str) -> None:
    if instance.mask_visib_path is None:
        raise PopcodeError(f"{instance.image_path}: the {augmentation} augmentation needs its mask_visib image")


class CropDataset(Dataset):
    """Dicts ``image`` (1, S, S) in [0, 1], ``target``, ``R_m2c`` (3, 3), ``obj_id`` and ``index``.

    ``targets_fn`` maps a list of instances to their targets ``(B, D)``.
    """

    def __init__(self, instances: Sequence[Instance], targets_fn: TargetsFn,
                 augmentation: Augmentation | None = PAPER_AUGMENTATION,
                 backgrounds: Backgrounds | str | Path | None = None, crop_size: int = 128, seed: int = 0,
                 cache_dir: str | Path | None = None, progress: bool = False) -> None:
        if len(instances) == 0:
            raise PopcodeError("no instances to make training samples from")
        self.instances = list(instances)
        self.targets_fn = targets_fn
        self.augmentation = augmentation
        self.backgrounds = backgrounds if isinstance(backgrounds, Backgrounds) else Backgrounds(backgrounds)
        self.crop_size = crop_size
        self.margin = margin_for_shift(augmentation.max_shift_crop_px) if augmentation else 0
        self.cache = None if cache_dir is None else CropCache(self.instances, crop_size, self.margin, cache_dir,
                                                              progress)
        self.seed = seed
        self.epoch = 0
        self._bank: tuple[int, np.ndarray] | None = None

    def set_epoch(self, epoch: int) -> None:
        """Draw new augmentations: the generator of each sample is seeded by (seed, epoch, index)."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.instances)

    def draw(self, index: int) -> tuple[AugmentationDraw | None, np.random.Generator]:
        """The augmentation a sample gets in this epoch, and the generator for its random content."""
        rng = np.random.default_rng([self.seed, self.epoch, index])
        if self.augmentation is None:
            return None, rng
        return self.augmentation.draw(rng, self.instances[index].rendered), rng

    def stored_crop(self, index: int) -> np.ndarray:
        """Image and visible mask ``(2, S + 2 margin, S + 2 margin)`` uint8 of one instance."""
        if self.cache is not None:
            return self.cache[index]
        return crop_with_margin(self.instances[index], self.crop_size, self.margin)

    def _background(self, rng: np.random.Generator) -> np.ndarray:
        if self._bank is None or self._bank[0] != self.epoch:
            bank_rng = np.random.default_rng([self.seed, self.epoch, len(self.instances)])
            count = min(BACKGROUNDS_PER_EPOCH, len(self.instances))
            self._bank = (self.epoch, np.stack([self.backgrounds.sample(bank_rng, self.crop_size)
                                                for _ in range(count)]))
        patch = self._bank[1][int(rng.integers(len(self._bank[1])))]
        patch = np.rot90(patch, int(rng.integers(4)))
        return patch[:, ::-1] if rng.random() < 0.5 else patch

    def crop(self, index: int) -> np.ndarray:
        """The augmented crop ``(S, S)`` float32 in [0, 1] of one instance."""
        instance = self.instances[index]
        augment, rng = self.draw(index)
        stored = self.stored_crop(index)
        # The shift (the paper's +-5 crop px) picks a window of the stored crop, to the nearest pixel.
        dx, dy = (int(round(v)) for v in augment.shift_crop_px) if augment else (0, 0)
        rows = slice(self.margin + dy, self.margin + dy + self.crop_size)
        cols = slice(self.margin + dx, self.margin + dx + self.crop_size)
        crop = stored[0, rows, cols].astype(np.float32) / 255.0
        if augment is None:
            return crop
        crop = crop + augment.brightness
        if augment.background:
            _require_mask(instance, "background")
            # Compositing the cropped mask as alpha equals pasting before the crop, with soft edges.
            alpha = stored[1, rows, cols].astype(np.float32) / 255.0
            crop = alpha * crop + (1.0 - alpha) * self._background(rng)
        if augment.occlusion:
            _require_mask(instance, "occlusion")
            alpha = occluder_alpha(rng, stored[1, rows, cols].astype(np.float32) / 255.0,
                                   self.augmentation.occlusion_max_fraction)
            occluder = self._background(rng) * rng.uniform(0.3, 1.0) + rng.uniform(0.0, 0.4)
            crop = alpha * occluder + (1.0 - alpha) * crop
        if augment.noise:
            crop = crop + self.augmentation.noise_sigma * rng.standard_normal(crop.shape, dtype=np.float32)
        return np.clip(crop, 0.0, 1.0).astype(np.float32)

    def _sample(self, index: int, target: np.ndarray) -> dict[str, Any]:
        instance = self.instances[index]
        return {
            "image": torch.from_numpy(self.crop(index))[None],
            "target": torch.from_numpy(np.asarray(target, dtype=np.float32)),
            "R_m2c": torch.from_numpy(instance.R_m2c.astype(np.float32)),
            "obj_id": instance.obj_id,
            "index": index,
        }

    def __getitem__(self, index: int) -> dict[str, Any]:
        return self._sample(index, self.targets_fn([self.instances[index]])[0])

    def __getitems__(self, indices: Sequence[int]) -> list[dict[str, Any]]:
        """A DataLoader batch: the targets in one call of ``targets_fn``."""
        targets = self.targets_fn([self.instances[i] for i in indices])
        return [self._sample(i, target) for i, target in zip(indices, targets, strict=True)]
