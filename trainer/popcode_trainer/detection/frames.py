"""Whole frames and their boxes for the detector, read from BOP scene splits (the renders the project already
makes), brought to the detector's input by the runtime's own :func:`detector_input` (a frame of another aspect
letterboxed, its boxes with it), and augmented.

The augmentation is what a camera changes and a render does not: zoom and framing (a crop of the frame, so parts
appear larger and cut by its border), exposure, contrast, blur and sensor noise. No flips: a mirrored part is not
a view of that part. With ``detector.negative_share`` some training frames are replaced by generated frames with
nothing to find (:func:`negative_frame`): a detector that has only seen bins full of parts finds parts in a blank
or noisy frame (issue 62, bench/results/empty-frames.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from torch.utils.data import Dataset
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.split import scene_folders, scene_ground_truth, split_images
from popcode_runtime.geometry.crop import read_image_file
from popcode_runtime.geometry.letterbox import Letterbox
from popcode_runtime.inference.detector import detector_input

from .config import DetectorConfig

MIN_KEPT_AREA = 0.4  # a box cut by a zoom's window stays a target while this share of it remains
MIN_SIDE_PX = 2.0  # and while it is at least this wide and tall


@dataclass(frozen=True)
class Frame:
    """One frame's targets: boxes ``(N, 4)`` x0, y0, x1, y1 in the detector input's pixels and class indices."""

    key: tuple[str, int, int]  # split, scene_id, im_id
    path: Path
    boxes: np.ndarray
    labels: np.ndarray


def read_frames(splits: Sequence[str | Path], obj_ids: Sequence[int], config: DetectorConfig) -> list[Frame]:
    """Every annotated image of the scene ``splits`` with its instances of ``obj_ids`` at least
    ``config.min_visib_fract`` visible (the box of ``config.box_kind``), scaled to the detector's input.

    An image with no such instance (``render --empty-share`` writes some: an empty bin, distractors only) is a
    frame with an empty target, all background to the detector's loss: the negatives that teach it to leave an
    empty frame alone."""
    classes = {obj_id: index for index, obj_id in enumerate(obj_ids)}
    frames = []
    for split in map(Path, splits):
        images = split_images(split)
        for scene_dir in scene_folders(split):
            scene_id = int(scene_dir.name)
            for im_id, selected in scene_ground_truth(scene_dir, config.box_kind, config.min_visib_fract,
                                                      set(classes)):
                if (scene_id, im_id) not in images:
                    raise PopcodeError(f"{scene_dir}: image {im_id} is annotated but has no image file")
                boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (gt.box for gt in selected)],
                                 np.float32).reshape(-1, 4)
                frames.append(Frame((str(split), scene_id, im_id), images[(scene_id, im_id)].path, boxes,
                                    np.array([classes[gt.obj_id] for gt in selected], np.int64)))
    if not frames:
        raise PopcodeError(f"no annotated images of objects {list(obj_ids)} in {', '.join(map(str, splits))}")
    return frames


def held_out(frames: Sequence[Frame], fraction: float, seed: int) -> tuple[list[Frame], list[Frame]]:
    """Training and validation frames, split by image with a seeded draw (the same every run). A ``fraction`` above
    0 holds out at least one image, so a validation loss is what it asked for; one that leaves no image to train on
    is refused before any is read."""
    order = np.random.default_rng(seed).permutation(len(frames))
    count = max(int(round(fraction * len(frames))), int(fraction > 0))
    if count >= len(frames):
        raise PopcodeError(f"detector.val_fraction {fraction:g} holds out {count} of the {len(frames)} annotated "
                           "images, leaving none to train on: lower it (0: no validation loss), or give more images")
    val = set(order[:count].tolist())
    return [f for i, f in enumerate(frames) if i not in val], [f for i, f in enumerate(frames) if i in val]


class FrameSet(Dataset):
    """Frames at the detector's input size, held in memory as 8-bit grey; ``augment`` draws each frame's changes
    from (seed, epoch, index), so a resumed run sees the same epochs."""

    def __init__(self, frames: Sequence[Frame], config: DetectorConfig, augment: bool, progress: bool = True) -> None:
        self.config, self.augment, self.epoch = config, augment, 0
        self.frames, self.pixels, self.boxes = list(frames), [], []
        size = (config.input_width, config.input_height)
        for frame in tqdm(self.frames, desc="reading frames", unit="img", disable=not progress, leave=False):
            image = read_image_file(frame.path)
            self.pixels.append(np.round(detector_input(image, *size) * 255).astype(np.uint8))
            fit = Letterbox.fit((image.shape[1], image.shape[0]), size)
            self.boxes.append(fit.to_input(frame.boxes).astype(np.float32))

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        image = self.pixels[index].astype(np.float32) / 255.0
        boxes, labels = self.boxes[index], self.frames[index].labels
        if self.augment:
            rng = np.random.default_rng([self.config.seed, self.epoch, index])
            # no draw at 0: the same augmentation stream as before the option
            if self.config.negative_share and rng.random() < self.config.negative_share:
                image, boxes, labels = negative_frame(image.shape, rng), boxes[:0], labels[:0]
            else:
                image, boxes, labels = _zoom(image, boxes, labels, rng)
            image = _camera_look(image, rng)
        return torch.from_numpy(np.ascontiguousarray(image))[None], {
            "boxes": torch.from_numpy(np.ascontiguousarray(boxes, np.float32)).reshape(-1, 4),
            "labels": torch.from_numpy(np.ascontiguousarray(labels, np.int64))}


def negative_frame(shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """A frame without parts, of one of four kinds: a flat level, a linear gradient, pixel noise (Gaussian about a
    level or uniform over a range) or blurred noise (a texture at a random scale)."""
    rows, cols = shape
    kind = rng.integers(4)
    if kind == 0:
        return np.full(shape, rng.uniform(0.0, 1.0), np.float32)
    if kind == 1:
        angle, low, high = rng.uniform(0, 2 * np.pi), rng.uniform(0.0, 1.0), rng.uniform(0.0, 1.0)
        ys, xs = np.mgrid[0:rows, 0:cols] / max(rows, cols)
        ramp = xs * np.cos(angle) + ys * np.sin(angle)
        ramp = (ramp - ramp.min()) / max(np.ptp(ramp), 1e-6)
        return (low + (high - low) * ramp).astype(np.float32)
    if kind == 2:
        if rng.random() < 0.5:
            noise = rng.normal(rng.uniform(0.0, 1.0), rng.uniform(0.0, 0.3), shape)
        else:
            low = rng.uniform(0.0, 1.0)
            noise = rng.uniform(low, rng.uniform(low, 1.0), shape)
        return np.clip(noise, 0.0, 1.0).astype(np.float32)
    texture = cv2.GaussianBlur(rng.random(shape, np.float32), (0, 0), rng.uniform(1.0, 12.0))
    texture = (texture - texture.mean()) / max(float(texture.std()), 1e-6)
    return np.clip(rng.uniform(0.2, 0.8) + rng.uniform(0.05, 0.3) * texture, 0.0, 1.0).astype(np.float32)


def _zoom(image: np.ndarray, boxes: np.ndarray, labels: np.ndarray,
          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Half the frames: a window of 1/1.6 to 1 of the frame at a random place, scaled back to the frame's size."""
    if rng.random() < 0.5:
        return image, boxes, labels
    rows, cols = image.shape
    scale = rng.uniform(1.0, 1.6)
    width, height = cols / scale, rows / scale
    x0, y0 = rng.uniform(0, cols - width), rng.uniform(0, rows - height)
    warp = np.array([[scale, 0, -x0 * scale], [0, scale, -y0 * scale]], np.float32)
    image = cv2.warpAffine(image, warp, (cols, rows), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    moved = (boxes - [x0, y0, x0, y0]) * scale
    clipped = np.clip(moved, 0, [cols, rows, cols, rows])
    keep = (_area(clipped) >= MIN_KEPT_AREA * np.maximum(_area(moved), 1e-6)) & \
        (clipped[:, 2] - clipped[:, 0] >= MIN_SIDE_PX) & (clipped[:, 3] - clipped[:, 1] >= MIN_SIDE_PX)
    return image, clipped[keep], labels[keep]


def _area(boxes: np.ndarray) -> np.ndarray:
    return np.clip(boxes[:, 2] - boxes[:, 0], 0, None) * np.clip(boxes[:, 3] - boxes[:, 1], 0, None)


def _camera_look(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Exposure, contrast, gamma, a slight blur on some frames and grain."""
    image = np.clip((image - 0.5) * rng.uniform(0.6, 1.4) + 0.5 + rng.uniform(-0.15, 0.15), 0.0, 1.0)
    image = image ** rng.uniform(0.7, 1.4)
    if rng.random() < 0.3:
        image = cv2.GaussianBlur(image, (0, 0), rng.uniform(0.3, 1.2))
    noise = rng.normal(0.0, rng.uniform(0.0, 0.03), image.shape).astype(np.float32)
    return np.clip(image + noise, 0.0, 1.0).astype(np.float32)


def collate(batch: list[tuple[torch.Tensor, dict[str, torch.Tensor]]]) -> tuple[list, list]:
    """torchvision's detectors take lists: images and targets."""
    return [image for image, _ in batch], [target for _, target in batch]


def split_objects(splits: Sequence[str | Path]) -> list[int]:
    """Every object id annotated in the scene ``splits``: what a detector learns unless told otherwise."""
    found: set[int] = set()
    for split in map(Path, splits):
        for scene_dir in scene_folders(split):
            found.update(gt.obj_id for _, selected in scene_ground_truth(scene_dir, "bbox_obj", 0.0)
                         for gt in selected)
    if not found:
        raise PopcodeError(f"no annotated objects in {', '.join(map(str, splits))}")
    return sorted(found)
