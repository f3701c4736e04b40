"""A tiny in-test data set with the ``CropDataset`` item contract: crops of a rotated,
asymmetric 3-D point set drawn with OpenCV (no renderer, no files)."""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset

from popcode_runtime.geometry.rotations import random_rotations

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
# Three arms of different lengths from the origin: no rotation maps the shape onto itself.
ARMS = np.array([[1.0, 0.0, 0.0], [0.0, 0.6, 0.0], [0.0, 0.0, 0.35]])
POINTS = np.concatenate([np.linspace(0, 1, 12)[:, None] * arm for arm in ARMS])


def draw(R: np.ndarray, size: int = 128) -> np.ndarray:
    """Grey float32 ``(size, size)``: points nearer the camera are brighter and drawn last."""
    camera = POINTS @ R.T
    image = np.zeros((size, size), np.float32)
    for x, y, z in camera[np.argsort(-camera[:, 2])]:
        centre = (int(size / 2 + 0.35 * size * x), int(size / 2 + 0.35 * size * y))
        cv2.circle(image, centre, 4, float(0.6 - 0.35 * z), -1)
    return image


class RotatedPoints(Dataset):
    """``count`` crops with uniform random rotations; ``instances[i]`` has K and a box for allocentric targets."""

    def __init__(self, count: int, target_fn: Callable[[SimpleNamespace], np.ndarray], seed: int = 0,
                 obj_id: int = 1, size: int = 128) -> None:
        rng = np.random.default_rng(seed)
        boxes = rng.uniform([100, 80, 60, 60], [400, 300, 120, 120], size=(count, 4))
        self.instances = [SimpleNamespace(obj_id=obj_id, R_m2c=R, K=K, box=tuple(box))
                          for R, box in zip(random_rotations(count, rng), boxes, strict=True)]
        self.images = [draw(inst.R_m2c, size) for inst in self.instances]
        self.targets = [np.asarray(target_fn(inst), np.float32) for inst in self.instances]

    def __len__(self) -> int:
        return len(self.instances)

    def __getitem__(self, index: int) -> dict:
        inst = self.instances[index]
        return {
            "image": torch.from_numpy(self.images[index][None]),
            "target": torch.from_numpy(self.targets[index]),
            "R_m2c": torch.from_numpy(inst.R_m2c.astype(np.float32)),
            "obj_id": inst.obj_id,
            "index": index,
        }
