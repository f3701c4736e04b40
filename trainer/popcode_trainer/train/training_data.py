"""BOP splits -> the pooled objects, a train/validation split and the crop data sets.

Validation holds out whole images (scene, image), so crops of one frame never
sit on both sides.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from popcode_runtime.base.errors import PopcodeError

from ..data.augment import Augmentation
from ..data.bop import Instance, read_bop_split
from ..data.box_noise import box_noise_preset
from ..data.samples import CropDataset
from ..data.symmetry_check import check_models_symmetries
from .config import Config
from .distributed import launched_world_size
from .loop import network_config
from .network import check_trainable
from .representations import OutputRepresentation, build_representation
from .run_files import CROP_CACHE_FOLDER


@dataclass
class TrainingData:
    representation: OutputRepresentation
    train_set: CropDataset
    val_set: CropDataset | None  # None when data.val_fraction is 0
    val_instances: list[Instance]


def read_instances(config: Config) -> tuple[list[Instance], dict[int, dict[str, Any]]]:
    """Every usable instance of the configured splits and the objects' ``models_info`` entries."""
    data = config.data
    if not data.splits or not data.models_dir:
        raise PopcodeError("set data.splits (BOP split folders) and data.models_dir in the config")
    obj_ids = list(data.obj_ids) or None
    instances: list[Instance] = []
    models_info: dict[int, dict[str, Any]] = {}
    for split_dir in data.splits:
        split = read_bop_split(split_dir, data.models_dir, obj_ids=obj_ids,
                               min_visib_fract=data.min_visib_fract, box=data.box)
        instances += split.instances
        models_info.update(split.models_info)
    if not instances:
        raise PopcodeError(f"no instances with visib_fract >= {data.min_visib_fract} of objects "
                           f"{obj_ids or 'any'} in {list(data.splits)}")
    used = sorted({inst.obj_id for inst in instances})
    check_models_symmetries(data.models_dir, models_info, used)
    return instances, {obj_id: dict(models_info[obj_id]) for obj_id in used}


def split_by_image(instances: list[Instance], val_fraction: float, seed: int) -> tuple[list[Instance],
                                                                                     list[Instance]]:
    """Hold out ``val_fraction`` of the images (seeded), with all their instances."""
    keys = sorted({(str(inst.image_path), inst.scene_id, inst.im_id) for inst in instances})
    order = np.random.default_rng(seed).permutation(len(keys))
    held_out = {keys[i] for i in order[: int(round(val_fraction * len(keys)))]}
    val = [inst for inst in instances if (str(inst.image_path), inst.scene_id, inst.im_id) in held_out]
    train = [inst for inst in instances if (str(inst.image_path), inst.scene_id, inst.im_id) not in held_out]
    return train, val


@dataclass(frozen=True)
class TrainingSplit:
    """The configured splits, read once for everything a command does with them (train, parity crops, calibration)."""

    instances: list[Instance]  # every usable instance
    objects: dict[int, dict[str, Any]]  # models_info entry of each object used
    train: list[Instance]
    val: list[Instance]  # the held-out images' instances (:func:`split_by_image`)


def read_training_split(config: Config) -> TrainingSplit:
    """Read the configured splits and hold out the validation images."""
    instances, objects = read_instances(config)
    train, val = split_by_image(instances, config.data.val_fraction, config.train.seed)
    return TrainingSplit(instances, objects, train, val)


def sampling_weights(instances: list[Instance], splits: tuple[str, ...], split_weights: tuple[float, ...]
                     ) -> list[float] | None:
    """Per-instance chances that give each split ``split_weights``' share of an epoch (None: every crop once)."""
    if not split_weights:
        return None
    folders = [Path(split).absolute() for split in splits]
    owner = [next(i for i, folder in enumerate(folders) if Path(inst.image_path).absolute().is_relative_to(folder))
             for inst in instances]
    counts = np.bincount(owner, minlength=len(folders))
    return [split_weights[i] / counts[i] for i in owner]


def build_training_data(config: Config, progress: bool = True, split: TrainingSplit | None = None) -> TrainingData:
    """Instances, representation and data sets of ``config`` (``split``: already read); training crops are cached
    in ``data.cache_dir``, by default in the run folder."""
    split = split or read_training_split(config)
    code, cfg = config.code, config.train
    representation = build_representation(cfg.representation, split.objects, code.n_axes, code.n_angles,
                                          code.sigma_deg, cfg.rotation_frame, cfg.num_hypotheses,
                                          code.sigma_from_symmetries, cfg.loss)
    # before the crops are cached: a network that cannot be built or trained is named before any progress bar
    check_trainable(network_config(config, representation), max(1, cfg.batch_size // launched_world_size()))
    train, val = split.train, split.val
    data = config.data
    augmentation = Augmentation(noise_sigma=data.noise_sigma, noise_p=data.noise_p,
                                occlusion_p=data.occlusion_p) if data.augment else None
    size = data.crop_size
    cache = Path(data.cache_dir) if data.cache_dir else Path(cfg.out_dir) / CROP_CACHE_FOLDER
    return TrainingData(
        representation=representation,
        train_set=CropDataset(train, representation.targets, augmentation=augmentation, crop_size=size, seed=cfg.seed,
                              cache_dir=cache, progress=progress, background=data.background,
                              box_noise=box_noise_preset(data.box_noise), box_noise_p=data.box_noise_p,
                              weights=sampling_weights(train, data.splits, data.split_weights)),
        val_set=CropDataset(val, representation.targets, augmentation=None, crop_size=size, seed=cfg.seed,
                            cache_dir=cache, progress=progress) if val else None,
        val_instances=val,
    )


def validation_crops(config: Config, count: int = 64,
                     split: TrainingSplit | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``count`` un-augmented validation crops ``(N, 1, S, S)`` and their object ids ``(N,)`` (``split``:
    already read; every instance when none is held out).

    The export's parity check input and int8's calibration crops; the ids pick
    each crop's symmetries for the pose agreement. They are spread evenly over
    the held-out instances, which come ordered by split and object: the first
    ``count`` would all be the first object's clean renders, and int8 would
    be calibrated on no other part and no scene.
    """
    split = split or read_training_split(config)
    pool = split.val or split.instances
    picks = np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int)
    chosen = [pool[i] for i in picks]
    crops = CropDataset(chosen, lambda batch: np.zeros((len(batch), 1), np.float32), augmentation=None,
                        crop_size=config.data.crop_size, seed=config.train.seed)
    images = np.stack([crops[i]["image"].numpy() for i in range(len(crops))])
    return images, np.array([inst.obj_id for inst in chosen], dtype=np.int64)
