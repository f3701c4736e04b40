"""Crops of every instance decoded once into a memory-mapped uint8 file, so epochs skip PNG decoding.

A training step spent about a third of its time decoding PNGs and masks and cropping them, one
sample at a time (``bench/results/training.md``). Crops and visible masks are stored at
``crop_size + 2 * margin`` pixels around the runtime's crop, so the shift augmentation is a slice
of the stored crop instead of a new crop of the image. The file is named by a hash of what makes
it (image and mask paths with their sizes and modification times, boxes, crop geometry), so a
changed split or crop setting builds a new one; it is written under a temporary name and renamed,
so an interrupted build leaves nothing that a later run would trust.
"""

from __future__ import annotations

import hashlib
import math
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from pathlib import Path

import numpy as np
from tqdm import tqdm

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.files import atomic_file, atomic_path, remove_stale_temporaries
from popcode_runtime.geometry.crop import CROP_PADDING, crop_square, read_image

from .bop import Instance, check_image_matches

CACHE_FORMAT = 2  # bump when what is stored changes
CACHE_SUFFIX = ".crops.npy"
BOX_NOISE_CONTEXT = 0.25  # of the crop side, stored on each side when training on detector-like boxes
SIZES_SUFFIX = ".sizes.npy"  # beside the crops: (N, 2) width, height of each instance's image
# OpenCV decodes without the GIL, so threads fill the cache side by side; each takes a run of consecutive
# instances, which share their scene's image (read once per run).
CACHE_THREADS = 8
CHUNKS_PER_THREAD = 4


def margin_for_shift(max_shift_crop_px: float) -> int:
    """Pixels of context kept on each side of a crop so that a shift of up to ``max_shift_crop_px`` is a slice."""
    return int(math.ceil(max(0.0, max_shift_crop_px)))


def margin_for_box_noise(crop_size: int) -> int:
    """Extra pixels of context kept on each side for crops of detector-like boxes: a quarter of the crop."""
    return int(math.ceil(BOX_NOISE_CONTEXT * crop_size))


def window_affine(box: Sequence[float], window_box: Sequence[float], crop_size: int, margin: int,
                  shift_crop_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray | None:
    """The ``(2, 3)`` map from pixels of the runtime's crop of ``window_box`` to pixels of the stored crop of ``box``
    (for ``cv2.warpAffine`` with ``WARP_INVERSE_MAP``), shifted by ``shift_crop_px``; None when the window
    reaches past the stored margin."""
    x, y, w, h = (float(v) for v in box)
    wx, wy, ww, wh = (float(v) for v in window_box)
    side, window_side = max(w, h) * CROP_PADDING, max(ww, wh) * CROP_PADDING  # image px of each square
    zoom = window_side / side
    stored_px = crop_size / side  # stored-crop pixels per image pixel
    outer = crop_size + 2 * margin
    offset = [(0.5 - crop_size / 2) * zoom + (window_centre - centre) * stored_px + outer / 2 - 0.5 + shift
              for window_centre, centre, shift in ((wx + ww / 2, x + w / 2, shift_crop_px[0]),
                                                   (wy + wh / 2, y + h / 2, shift_crop_px[1]))]
    reach = [(start, start + zoom * (crop_size - 1)) for start in offset]
    if min(low for low, _ in reach) < -0.5 or max(high for _, high in reach) > outer - 0.5:
        return None
    return np.array([[zoom, 0.0, offset[0]], [0.0, zoom, offset[1]]])


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[0, 1] float -> uint8, rounded (the precision of the PNGs the crops come from)."""
    return np.round(np.clip(image, 0.0, 1.0) * 255.0).astype(np.uint8)


def last_image_reader() -> Callable[[Path], np.ndarray]:
    """:func:`read_image` that keeps the last image it read: a scene's instances come one after another."""
    last: dict[Path, np.ndarray] = {}

    def read(path: Path) -> np.ndarray:
        if path not in last:
            last.clear()
            last[path] = read_image(path)
        return last[path]
    return read


def crop_with_margin(instance: Instance, crop_size: int, margin: int,
                     read: Callable[[Path], np.ndarray] = read_image) -> tuple[np.ndarray, tuple[int, int]]:
    """Image and visible mask ``(2, C, C)`` uint8 with ``C = crop_size + 2 * margin``, centred like the runtime crop,
    and the image's (width, height); ``read`` reads the image (the mask is read on its own).

    The inner ``crop_size`` square is the runtime's crop of the box; the mask
    is zero for instances without one (real images: no background pasting).
    """
    outer = crop_size + 2 * margin
    padding = CROP_PADDING * outer / crop_size
    full = read(instance.image_path)
    check_image_matches(instance, full.shape[1], full.shape[0])
    image = crop_square(full, instance.box, outer, padding)
    mask = np.zeros_like(image)
    if instance.mask_visib_path is not None:
        full_mask = read_image(instance.mask_visib_path)
        if full_mask.shape[:2] != full.shape[:2]:
            raise PopcodeError(f"{instance.mask_visib_path} is {full_mask.shape[1]}x{full_mask.shape[0]} px, its "
                               f"image {instance.image_path} {full.shape[1]}x{full.shape[0]}: they must match")
        mask = crop_square(full_mask, instance.box, outer, padding)
    return np.stack([to_uint8(image), to_uint8(mask)]), (full.shape[1], full.shape[0])


def _fingerprint(instances: Sequence[Instance], crop_size: int, margin: int) -> str:
    digest = hashlib.sha256(f"{CACHE_FORMAT} {crop_size} {margin} {CROP_PADDING}".encode())
    stats: dict[Path, str] = {}
    for instance in instances:
        for path in (instance.image_path, instance.mask_visib_path):
            if path is not None and path not in stats:
                if not Path(path).is_file():
                    raise PopcodeError(f"image file not found: {path}")
                stat = Path(path).stat()
                stats[path] = f"{stat.st_size}:{stat.st_mtime_ns}"
            digest.update(f"{path}={stats.get(path, '-')};".encode())
        digest.update(np.asarray(instance.box, dtype=np.float64).tobytes())
    return digest.hexdigest()[:20]


class CropCache:
    """The ``(N, 2, C, C)`` uint8 crops of ``instances`` in a file under ``folder``; built on first use.

    Opened read-only as a memory map in each process that reads it (workers
    included), so paper-size data does not have to fit in memory.
    """

    def __init__(self, instances: Sequence[Instance], crop_size: int, margin: int, folder: str | Path,
                 progress: bool = True) -> None:
        self.path = Path(folder) / f"{_fingerprint(instances, crop_size, margin)}{CACHE_SUFFIX}"
        self.sizes_path = self.path.with_name(self.path.name.replace(CACHE_SUFFIX, SIZES_SUFFIX))
        self._array: np.ndarray | None = None
        self._sizes: np.ndarray | None = None
        if not self.path.exists():
            self._build(instances, crop_size, margin, progress)

    def _build(self, instances: Sequence[Instance], crop_size: int, margin: int, progress: bool) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        outer = crop_size + 2 * margin
        sizes = np.zeros((len(instances), 2), np.int64)
        threads = max(1, min(CACHE_THREADS, os.cpu_count() or 1))
        runs = np.array_split(np.arange(len(instances)), threads * CHUNKS_PER_THREAD)
        stop, counted = threading.Event(), threading.Lock()

        def fill(rows: np.ndarray, crops: np.ndarray, bar: tqdm) -> None:
            read = last_image_reader()
            for index in rows:
                if stop.is_set():  # another run failed, or the build was interrupted
                    return
                crops[index], sizes[index] = crop_with_margin(instances[index], crop_size, margin, read)
                with counted:
                    bar.update()

        remove_stale_temporaries(self.path)
        remove_stale_temporaries(self.sizes_path)
        # Both files are replaced whole, so a process reading a cache another process rebuilds (runs sharing
        # data.cache_dir) never sees a partial file; the sizes first: the crops' file means both are complete.
        with atomic_path(self.path) as temporary:
            array = np.lib.format.open_memmap(temporary, mode="w+", dtype=np.uint8,
                                              shape=(len(instances), 2, outer, outer))
            with tqdm(total=len(instances), desc="caching crops", unit="crop", disable=not progress,
                      leave=False) as bar:
                pool = ThreadPoolExecutor(threads)
                try:
                    futures = [pool.submit(fill, rows, array, bar) for rows in runs if len(rows)]
                    wait(futures, return_when=FIRST_EXCEPTION)
                    for future in futures:
                        if future.done() and future.exception() is not None:
                            raise future.exception()  # the first run that failed
                finally:
                    stop.set()  # a no-op once every run is done; otherwise the threads stop at their next crop
                    pool.shutdown(cancel_futures=True)
            array.flush()
            del array
            with atomic_file(self.sizes_path) as handle:
                np.save(handle, sizes)

    @property
    def array(self) -> np.ndarray:
        if self._array is None:
            self._array = np.load(self.path, mmap_mode="r")
        return self._array

    def __getitem__(self, index: int) -> np.ndarray:
        return np.asarray(self.array[index])

    def image_size(self, index: int) -> tuple[int, int]:
        """(width, height) of the instance's image."""
        if self._sizes is None:
            self._sizes = np.load(self.sizes_path)
        width, height = self._sizes[index]
        return int(width), int(height)

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_array": None, "_sizes": None}  # each worker maps the file itself
