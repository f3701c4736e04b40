"""Training samples: the runtime's crop of each instance, augmented, with its target.

Every sample draws from a generator seeded by ``(seed, epoch, index)``, so a sample is the same
whichever DataLoader worker makes it and in whatever order; call :meth:`CropDataset.set_epoch`
before each epoch (with ``persistent_workers=False``, the default, workers see the new epoch).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from popcode_runtime.crop import CROP_PADDING, crop_square, read_image
from popcode_runtime.errors import PopcodeError

from .augment import Augmentation, AugmentationDraw, Backgrounds
from .bop import Instance

PAPER_AUGMENTATION = Augmentation()


class CropDataset(Dataset):
    """Dicts ``image`` (1, S, S) in [0, 1], ``target``, ``R_m2c`` (3, 3), ``obj_id`` and ``index``."""

    def __init__(self, instances: Sequence[Instance], target_fn: Callable[[Instance], np.ndarray],
                 augmentation: Augmentation | None = PAPER_AUGMENTATION,
                 backgrounds: Backgrounds | str | Path | None = None, crop_size: int = 128, seed: int = 0) -> None:
        if len(instances) == 0:
            raise PopcodeError("no instances to make training samples from")
        self.instances = list(instances)
        self.target_fn = target_fn
        self.augmentation = augmentation
        self.backgrounds = backgrounds if isinstance(backgrounds, Backgrounds) else Backgrounds(backgrounds)
        self.crop_size = crop_size
        self.seed = seed
        self.epoch = 0

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

    def crop(self, index: int) -> np.ndarray:
        """The augmented crop ``(S, S)`` float32 in [0, 1] of one instance."""
        instance = self.instances[index]
        augment, rng = self.draw(index)
        shift_crop_px = augment.shift_crop_px if augment else (0.0, 0.0)
        # The shift is in crop pixels (the paper's +-5 px); crop_square moves in source pixels.
        source_px_per_crop_px = CROP_PADDING * max(instance.box[2], instance.box[3]) / self.crop_size
        shift_px = (shift_crop_px[0] * source_px_per_crop_px, shift_crop_px[1] * source_px_per_crop_px)
        crop = crop_square(read_image(instance.image_path), instance.box, self.crop_size, shift_px=shift_px)
        if augment is None:
            return crop
        crop = crop + augment.brightness
        if augment.background:
            if instance.mask_visib_path is None:
                raise PopcodeError(f"{instance.image_path}: the background augmentation needs its mask_visib image")
            # Compositing the cropped mask as alpha equals pasting before the crop, with soft edges.
            alpha = crop_square(read_image(instance.mask_visib_path), instance.box, self.crop_size, shift_px=shift_px)
            crop = alpha * crop + (1.0 - alpha) * self.backgrounds.sample(rng, self.crop_size)
        if augment.noise:
            crop = crop + rng.normal(0.0, self.augmentation.noise_sigma, crop.shape)
        return np.clip(crop, 0.0, 1.0).astype(np.float32)

    def __getitem__(self, index: int) -> dict[str, Any]:
        instance = self.instances[index]
        return {
            "image": torch.from_numpy(self.crop(index))[None],
            "target": torch.from_numpy(np.asarray(self.target_fn(instance), dtype=np.float32)),
            "R_m2c": torch.from_numpy(instance.R_m2c.astype(np.float32)),
            "obj_id": instance.obj_id,
            "index": index,
        }

