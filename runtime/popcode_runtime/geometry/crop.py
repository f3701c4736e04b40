"""Images in, network crops out (docs/design.md#crop) -- used for training and inference alike.

A box ``(x, y, w, h)`` in pixels becomes a square of side ``padding * max(w, h)``
centred on the box centre; what falls outside the image is 0. The square is
resized to ``size x size``, grey, float32 in [0, 1].

Boxes follow the BOP toolkit (``calc_2d_bbox``): ``(x, y)`` is the first pixel,
``w`` and ``h`` run from the first pixel's centre to the last one's, so with
OpenCV's pixel centres at whole coordinates the object spans ``x - 0.5`` to
``x + w + 0.5`` (:func:`box_edges`). Only the translation fit cares about this
half pixel; the crop uses the centre, which both readings share.
"""

from __future__ import annotations

import zlib
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from ..base.checks import integer, shown
from ..base.checks import path as checked_path
from ..base.errors import PopcodeError, library_step
from ..base.image_size import image_size

CROP_SIZE = 128
CROP_PADDING = 1.1
MIN_CROP_PADDING, MAX_CROP_PADDING = 1.0, 4.0  # the square is 1x to 4x the box's longer side
MAX_IMAGE_PIXELS = 1 << 30  # OpenCV's own default limit (CV_IO_MAX_IMAGE_PIXELS); read_image takes another
MAX_BOX_FACTOR = 4.0  # a box may be at most this many times the image's longer side (objects cut by the border)
MIN_BOX_PX = 1.0  # a box's longer side [px]; smaller boxes hold no object to see
MAX_SQUARE_PIXELS = 1 << 28  # the padded square before resizing: 1 GiB of float32
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_READ_BLOCK = 1 << 20  # bytes read at a time while checking a PNG's chunks

_GREY_WEIGHTS_RGB = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def read_image(path: str | Path, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Read an image file as grey float32 ``(H, W)`` in [0, 1] (8- or 16-bit, grey or colour)."""
    return to_grey(read_image_file(path, max_pixels))


def read_image_file(path: str | Path, max_pixels: int = MAX_IMAGE_PIXELS, what: str = "image",
                    as_stored: bool = False) -> np.ndarray:
    """An image file's pixels as stored (any bit depth; colour as RGB ``(H, W, 3)``): the one reader of images and
    depth images.

    Files of more than ``max_pixels`` pixels are refused from their header,
    before OpenCV decodes (and allocates) them, and a PNG whose chunks are
    torn or damaged before libpng prints its own complaint on stderr. ``what``
    names the file in errors. ``as_stored`` keeps every channel (alpha too) in
    OpenCV's order, untouched by colour handling: for depth images, whose
    channel count is then told as it is.
    """
    path = checked_path(path, f"{what} path")
    max_pixels = integer(max_pixels, "max_pixels", 1)
    if path.exists() and not path.is_file():
        raise PopcodeError(f"{what} {path} is not a regular file (a folder, FIFO or device)")
    if not path.is_file():
        raise PopcodeError(f"{what} file not found: {path}")
    with library_step(f"read the header of {what} {path}"):
        size = image_size(path)
    if size is not None and size[0] * size[1] > max_pixels:
        raise PopcodeError(f"{what} {path} is {size[0]}x{size[1]} = {size[0] * size[1]} pixels, more than the "
                           f"limit of {max_pixels}")
    with library_step(f"read {what} {path}"):
        _check_png_chunks(path, what)
    with library_step(f"decode {what} {path} with OpenCV"):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED if as_stored else cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
    if image is None:
        raise PopcodeError(f"cannot read {what} {path}: not an image format OpenCV can decode")
    if image.shape[0] * image.shape[1] > max_pixels:
        raise PopcodeError(f"{what} {path} has {image.shape[0] * image.shape[1]} pixels, more than the limit of "
                           f"{max_pixels}")
    if image.ndim == 3 and not as_stored:
        image = image[..., :3][..., ::-1]  # OpenCV reads BGR(A); popcode works in RGB
    return image


def _check_png_chunks(path: Path, what: str) -> None:
    """Refuse a PNG that ends before its ``IEND`` chunk or has a chunk failing its CRC; other formats pass.

    libpng reports such a file on stderr itself (``libpng error: Read Error``), which no OpenCV log level
    silences: checked here, the file is named in one line instead.
    """
    with open(path, "rb") as handle:
        if handle.read(len(PNG_SIGNATURE)) != PNG_SIGNATURE:
            return
        while True:
            head = handle.read(8)  # the chunk's length and kind, then its data and CRC
            length, kind = (int.from_bytes(head[:4], "big"), head[4:]) if len(head) == 8 else (0, b"")
            crc, done = zlib.crc32(kind), 0
            while done < length and (block := handle.read(min(length - done, _READ_BLOCK))):
                crc, done = zlib.crc32(block, crc), done + len(block)
            stored = handle.read(4)
            if len(head) < 8 or done < length or len(stored) < 4:
                raise PopcodeError(f"cannot read {what} {path}: the PNG ends before its IEND chunk (a torn or "
                                   "truncated file)")
            if int.from_bytes(stored, "big") != crc:
                raise PopcodeError(f"cannot read {what} {path}: its PNG chunk {kind.decode('latin-1')!r} fails its "
                                   "CRC (a damaged file)")
            if kind == b"IEND":
                return


def check_image(image: np.ndarray) -> np.ndarray:
    """``image`` checked as :func:`to_grey` takes it, ``(H, W, 1)`` squeezed to ``(H, W)``; not converted.

    Cropping converts only the pixels a crop reads: converting a whole camera frame to float for every
    call can cost more than the network does (`popcode bench` end to end against inference).
    """
    if not isinstance(image, np.ndarray):
        raise PopcodeError(f"image must be a numpy array, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[..., 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise PopcodeError(f"image must have shape (H, W) or (H, W, 3), got {image.shape}")
    if image.shape[0] < 1 or image.shape[1] < 1:
        raise PopcodeError(f"image is empty: shape {image.shape}")
    if image.dtype not in (np.uint8, np.uint16, np.float32, np.float64):
        raise PopcodeError(f"unsupported image dtype {image.dtype}; use uint8, uint16 or float32 in [0, 1]")
    if image.dtype in (np.float32, np.float64):
        if not np.isfinite(image).all():
            raise PopcodeError("image contains NaN or inf pixels")
        if image.min() < 0.0 or image.max() > 1.0:
            raise PopcodeError(f"float image values must lie in [0, 1], got [{image.min():.3g}, {image.max():.3g}]")
    return image


def to_grey(image: np.ndarray) -> np.ndarray:
    """Grey float32 ``(H, W)`` in [0, 1] from grey ``(H, W)``/``(H, W, 1)`` or RGB ``(H, W, 3)``.

    uint8 is divided by 255, uint16 by 65535; float images must already lie in [0, 1].
    """
    image = check_image(image)
    grey = image.astype(np.float32)
    if image.dtype in (np.uint8, np.uint16):  # in place: a second whole-frame array costs more than the division
        grey /= 255.0 if image.dtype == np.uint8 else 65535.0
    if grey.ndim == 3:
        grey = grey @ _GREY_WEIGHTS_RGB
    return np.ascontiguousarray(grey)


def check_box(box: Sequence[float], image_shape: tuple[int, ...]) -> tuple[float, float, float, float]:
    """Validate a box ``(x, y, w, h)`` against an image; returns it as floats.

    A box partly outside the image is fine (zero fill); one wholly outside is
    not, nor one under a pixel or over ``MAX_BOX_FACTOR`` times the image's
    longer side (its crop would be mostly fill, and its square unbounded memory).
    """
    if isinstance(box, (str, bytes)) or not hasattr(box, "__len__") or len(box) != 4:
        raise PopcodeError(f"a box is 4 numbers x, y, w, h; got {shown(box, 80)}")
    try:
        x, y, w, h = (float(v) for v in box)
    except (TypeError, ValueError, OverflowError) as error:
        raise PopcodeError(f"a box is 4 numbers x, y, w, h; got {shown(box, 80)}") from error
    if any(isinstance(v, (str, bytes, bool, np.bool_)) for v in box):
        raise PopcodeError(f"a box is 4 numbers x, y, w, h; got {shown(box, 80)}")
    if not all(np.isfinite([x, y, w, h])):
        raise PopcodeError(f"box {shown(box, 80)} contains NaN or inf")
    if w <= 0 or h <= 0:
        raise PopcodeError(f"box {shown(box, 80)} is empty: width and height must be positive")
    if max(w, h) < MIN_BOX_PX:
        raise PopcodeError(f"box {shown(box, 80)} is smaller than a pixel")
    height, width = image_shape[:2]
    limit = MAX_BOX_FACTOR * max(height, width)
    if max(w, h) > limit:
        raise PopcodeError(f"box {shown(box, 80)} is larger than {MAX_BOX_FACTOR:g}x the {width}x{height} image "
                           f"({limit:g} px)")
    if x >= width or y >= height or x + w <= 0 or y + h <= 0:
        raise PopcodeError(f"box {shown(box, 80)} lies wholly outside the {width}x{height} image")
    return x, y, w, h


def check_padding(padding: float) -> float:
    """The crop padding as a finite float in ``[MIN_CROP_PADDING, MAX_CROP_PADDING]``."""
    if isinstance(padding, (bool, np.bool_, str, bytes)) or not isinstance(padding, (int, float, np.number)):
        raise PopcodeError(f"crop padding must be a number, got {padding!r}")
    if not (np.isfinite(padding) and MIN_CROP_PADDING <= padding <= MAX_CROP_PADDING):
        raise PopcodeError(f"crop padding must lie in [{MIN_CROP_PADDING:g}, {MAX_CROP_PADDING:g}], got {padding}")
    return float(padding)


def crop_square(
    image: np.ndarray,
    box: Sequence[float],
    size: int = CROP_SIZE,
    padding: float = CROP_PADDING,
    shift_px: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """One grey crop ``(size, size)`` float32 in [0, 1] from an image that :func:`to_grey` takes.

    ``shift_px`` moves the square by whole source pixels (used by the
    training augmentation); the padded side is rounded to whole pixels and
    shrunk with area interpolation, so large boxes do not alias.
    """
    image = check_image(image)
    x, y, w, h = check_box(box, image.shape)
    side = max(1, int(round(check_padding(padding) * max(w, h))))
    if side * side > MAX_SQUARE_PIXELS:
        raise PopcodeError(f"box {shown(box, 80)} needs a {side}x{side} crop square, more than the limit of "
                           f"{MAX_SQUARE_PIXELS} pixels")
    centre_x = x + w / 2.0 + shift_px[0]
    centre_y = y + h / 2.0 + shift_px[1]
    x0 = int(round(centre_x - side / 2.0))
    y0 = int(round(centre_y - side / 2.0))
    square = np.zeros((side, side), dtype=np.float32)
    height, width = image.shape[:2]
    src_x0, src_y0 = max(x0, 0), max(y0, 0)
    src_x1, src_y1 = min(x0 + side, width), min(y0 + side, height)
    if src_x1 > src_x0 and src_y1 > src_y0:
        square[src_y0 - y0 : src_y1 - y0, src_x0 - x0 : src_x1 - x0] = to_grey(image[src_y0:src_y1, src_x0:src_x1])
    interpolation = cv2.INTER_AREA if side > size else cv2.INTER_LINEAR
    return cv2.resize(square, (size, size), interpolation=interpolation)


def crop_batch(
    image: np.ndarray,
    boxes: Sequence[Sequence[float]],
    size: int = CROP_SIZE,
    padding: float = CROP_PADDING,
) -> np.ndarray:
    """Crops of many boxes in one image as the network input ``(N, 1, size, size)`` float32."""
    image = check_image(image)
    if isinstance(boxes, (str, bytes)) or not hasattr(boxes, "__len__"):
        raise PopcodeError(f"boxes must be a list of (x, y, w, h), got {type(boxes).__name__}")
    if len(boxes) == 0:
        raise PopcodeError("no boxes given")
    crops = [crop_square(image, box, size, padding) for box in boxes]
    return np.stack(crops)[:, None]


def box_edges(box: Sequence[float]) -> np.ndarray:
    """The silhouette's edges ``(x_min, y_min, x_max, y_max)`` [px, OpenCV] of a BOP box ``(x, y, w, h)``."""
    x, y, w, h = (float(v) for v in box)
    return np.array([x - 0.5, y - 0.5, x + w + 0.5, y + h + 0.5])


def box_from_edges(edges: Sequence[float]) -> tuple[float, float, float, float]:
    """The BOP box ``(x, y, w, h)`` of a silhouette with edges ``(x_min, y_min, x_max, y_max)``; inverts
    :func:`box_edges`."""
    x_min, y_min, x_max, y_max = (float(v) for v in edges)
    return x_min + 0.5, y_min + 0.5, x_max - x_min - 1.0, y_max - y_min - 1.0


def box_centre(box: Sequence[float]) -> np.ndarray:
    """Centre ``(2,)`` of a box ``(x, y, w, h)`` in pixels."""
    x, y, w, h = (float(v) for v in box)
    return np.array([x + w / 2.0, y + h / 2.0])
