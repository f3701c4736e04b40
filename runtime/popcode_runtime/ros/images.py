"""ROS image messages as the arrays popcode works on, and ``sensor_msgs/msg/CameraInfo`` as its checked camera.

Images: ``sensor_msgs/msg/Image`` in ``mono8``, ``mono16``, ``rgb8`` or ``bgr8`` (kept as stored: grey, or RGB
as popcode's readers give colour) and ``sensor_msgs/msg/CompressedImage`` (JPEG or PNG, decoded by OpenCV).
Depth: ``16UC1`` in millimetres and ``32FC1`` in metres (REP 118), NaN and inf meaning no reading (0 here).

Cameras: K from the message, checked against the image (its size, the principal point on it, a field of view a
camera has: :func:`~popcode_runtime.geometry.camera.camera_for_image`). The distortion model is honoured, never
ignored: ``plumb_bob`` and ``rational_polynomial`` with non-zero coefficients are undistorted with OpenCV into
the same K (the pose is then that of the pinhole camera K); fisheye models and any model OpenCV's pinhole model
does not have are refused.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..base.errors import PopcodeError, library_step
from ..geometry.camera import camera_for_image, parse_camera_matrix
from ..geometry.crop import MAX_IMAGE_PIXELS

IMAGE_TYPE, COMPRESSED_TYPE, CAMERA_INFO_TYPE = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
                                                 "sensor_msgs/msg/CameraInfo")
# encoding -> (stored type, channels, mm per unit for depth)
IMAGE_ENCODINGS = {"mono8": (np.uint8, 1), "mono16": (np.uint16, 1), "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3)}
DEPTH_ENCODINGS = {"16UC1": (np.uint16, 1.0), "32FC1": (np.float32, 1000.0)}
# Pinhole distortion models OpenCV's undistortion has (k1 k2 p1 p2 k3 [k4 k5 k6]).
PINHOLE_MODELS = {"plumb_bob": 5, "rational_polynomial": 8}


def _pixels(msg: Any, dtype: type, channels: int, what: str, max_pixels: int) -> np.ndarray:
    """The ``(H, W)`` or ``(H, W, C)`` array a raw ``Image`` holds, its rows' padding (``step``) dropped."""
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    if height < 1 or width < 1 or height * width > max_pixels:
        raise PopcodeError(f"{what} is {width}x{height} pixels: not an image of 1 to {max_pixels} pixels")
    row = width * channels * np.dtype(dtype).itemsize
    data = np.asarray(msg.data, dtype=np.uint8)
    if step < row or data.size < step * height:
        raise PopcodeError(f"{what} ({width}x{height} {msg.encoding}) holds {data.size} bytes in rows of {step}; it "
                           f"needs {height} rows of at least {row} bytes (a damaged message?)")
    stored = np.dtype(dtype).newbyteorder(">" if msg.is_bigendian else "<")
    pixels = np.ascontiguousarray(data[:step * height].reshape(height, step)[:, :row]).view(stored)
    pixels = pixels.astype(np.dtype(dtype), copy=False)  # native byte order
    return pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)


def image_array(msg: Any, msgtype: str, what: str, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """A camera image message's pixels: grey ``(H, W)`` uint8/uint16 or RGB ``(H, W, 3)`` uint8."""
    if msgtype == COMPRESSED_TYPE:
        with library_step(f"decode {what} ({msg.format!r}) with OpenCV"):
            image = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)
        if image is None or "compresseddepth" in msg.format.lower():
            raise PopcodeError(f"cannot decode {what}: format {msg.format!r} is not a JPEG or PNG OpenCV reads")
        if image.shape[0] * image.shape[1] > max_pixels:
            raise PopcodeError(f"{what} has {image.shape[0] * image.shape[1]} pixels, more than {max_pixels}")
        return image[..., ::-1] if image.ndim == 3 else image  # OpenCV decodes BGR; popcode works in RGB
    if msg.encoding not in IMAGE_ENCODINGS:
        raise PopcodeError(f"{what} has encoding {msg.encoding!r}; popcode reads {', '.join(IMAGE_ENCODINGS)} and "
                           "sensor_msgs/CompressedImage")
    pixels = _pixels(msg, *IMAGE_ENCODINGS[msg.encoding], what, max_pixels)
    return pixels[..., ::-1] if msg.encoding == "bgr8" else pixels


def depth_array(msg: Any, what: str, max_pixels: int = MAX_IMAGE_PIXELS) -> tuple[np.ndarray, float]:
    """A depth image message's readings ``(H, W)`` (0: no reading) and its millimetres per unit."""
    if msg.encoding not in DEPTH_ENCODINGS:
        raise PopcodeError(f"{what} has encoding {msg.encoding!r}; depth is read as "
                           f"{' or '.join(DEPTH_ENCODINGS)}")
    dtype, mm_per_unit = DEPTH_ENCODINGS[msg.encoding]
    depth = _pixels(msg, dtype, 1, what, max_pixels)
    if depth.dtype.kind == "f":
        depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    return depth, mm_per_unit


@dataclass
class Camera:
    """One ``CameraInfo``'s checked pinhole camera; :meth:`undistort` maps an image into it (nothing to do where
    the coefficients are zero)."""

    K: np.ndarray
    size: tuple[int, int]  # (width, height)
    maps: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)

    def undistort(self, image: np.ndarray, nearest: bool = False) -> np.ndarray:
        """``image`` as the pinhole camera K sees it (``nearest``: a depth image, whose readings are not blended)."""
        if self.maps is None:
            return image
        interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(image, *self.maps, interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def camera_from_info(info: Any, where: str) -> Camera:
    """The camera of a ``CameraInfo`` (``where`` names it in errors); its distortion undistorted or refused."""
    width, height = int(info.width), int(info.height)
    if width < 1 or height < 1 or width * height > MAX_IMAGE_PIXELS:
        raise PopcodeError(f"{where} is for {width}x{height} images: not a camera's image size")
    if int(info.binning_x) > 1 or int(info.binning_y) > 1 or int(info.roi.width) or int(info.roi.height):
        raise PopcodeError(f"{where} sets binning or a region of interest; popcode needs the full-resolution "
                           "camera (binning 0 or 1, no ROI)")
    try:
        K = parse_camera_matrix(np.asarray(info.k, dtype=np.float64))
        camera_for_image(K, (height, width))
    except PopcodeError as error:
        raise PopcodeError(f"{where}: {error}") from error
    model, coefficients = str(info.distortion_model), np.asarray(info.d, dtype=np.float64)
    if not np.isfinite(coefficients).all():
        raise PopcodeError(f"{where}: its distortion coefficients hold NaN or inf")
    if not coefficients.any() and model in (*PINHOLE_MODELS, ""):
        return Camera(K, (width, height))
    if model not in PINHOLE_MODELS:
        raise PopcodeError(f"{where} has distortion model {model!r}; popcode undistorts "
                           f"{' and '.join(PINHOLE_MODELS)} and refuses others (fisheye/equidistant images: "
                           "rectify them first, e.g. with image_proc)")
    if coefficients.size > PINHOLE_MODELS[model]:
        raise PopcodeError(f"{where}: {model} has at most {PINHOLE_MODELS[model]} coefficients, got "
                           f"{coefficients.size}")
    with library_step(f"compute the undistortion of {where} with OpenCV"):
        maps = cv2.initUndistortRectifyMap(K, coefficients, None, K, (width, height), cv2.CV_16SC2)
    return Camera(K, (width, height), maps)


def check_frame_size(camera: Camera, image: np.ndarray, where: str) -> None:
    """Refuse an image whose size is not the one its camera is for (K would be another image's)."""
    if (image.shape[1], image.shape[0]) != camera.size:
        raise PopcodeError(f"{where} is {image.shape[1]}x{image.shape[0]} but its CameraInfo is for "
                           f"{camera.size[0]}x{camera.size[1]} images: its K would be another image size's")
