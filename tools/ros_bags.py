"""Real ROS 2 bags for the ``popcode bag`` tests and benchmark, written by rosbags itself (SQLite3 or MCAP):
camera images in each encoding, ``CameraInfo`` and depth, from arrays the caller chooses; and the output bag read
back with rosbags' deserialiser."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from popcode_runtime.ros.images import CAMERA_INFO_TYPE, COMPRESSED_TYPE, IMAGE_TYPE
from popcode_runtime.ros.messages import typestore

IMAGE_TOPIC, INFO_TOPIC, DEPTH_TOPIC = "/camera/image_raw", "/camera/camera_info", "/camera/depth/image_raw"
FRAME_ID = "camera_optical_frame"
PERIOD_NS = 100_000_000  # 10 frames a second
START_NS = 1_700_000_000 * 1_000_000_000
# the camera of models/samples/bin.png (720 x 540; the README's --K)
SAMPLE_BIN_K = np.array([[864.0, 0.0, 359.5], [0.0, 864.0, 269.5], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Message:
    topic: str
    msgtype: str
    time_ns: int
    msg: Any


def _types() -> dict[str, Any]:
    return typestore().types


def header(time_ns: int, frame_id: str = FRAME_ID) -> Any:
    types = _types()
    stamp = types["builtin_interfaces/msg/Time"](sec=time_ns // 1_000_000_000, nanosec=time_ns % 1_000_000_000)
    return types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id)


def camera_info(time_ns: int, K: np.ndarray, size: tuple[int, int], model: str = "plumb_bob",
                d: Sequence[float] = (0.0,) * 5, frame_id: str = FRAME_ID) -> Message:
    """A ``CameraInfo`` of ``K`` for ``size`` (width, height) images."""
    types = _types()
    roi = types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    P = np.zeros(12)
    P[[0, 2, 5, 6, 10]] = K[0, 0], K[0, 2], K[1, 1], K[1, 2], 1.0
    msg = types[CAMERA_INFO_TYPE](header=header(time_ns, frame_id), height=size[1], width=size[0],
                                  distortion_model=model, d=np.asarray(d, dtype=np.float64),
                                  k=np.asarray(K, dtype=np.float64).reshape(9), r=np.eye(3).reshape(9), p=P,
                                  binning_x=0, binning_y=0, roi=roi)
    return Message(INFO_TOPIC, CAMERA_INFO_TYPE, time_ns, msg)


def image(time_ns: int, pixels: np.ndarray, encoding: str, topic: str = IMAGE_TOPIC,
          frame_id: str = FRAME_ID) -> Message:
    """A raw ``sensor_msgs/Image`` of ``pixels`` as they are stored in ``encoding`` (little-endian)."""
    channels = 1 if pixels.ndim == 2 else pixels.shape[2]
    data = np.ascontiguousarray(pixels).view(np.uint8).reshape(-1)
    msg = _types()[IMAGE_TYPE](header=header(time_ns, frame_id), height=pixels.shape[0], width=pixels.shape[1],
                               encoding=encoding, is_bigendian=0,
                               step=pixels.shape[1] * channels * pixels.dtype.itemsize, data=data)
    return Message(topic, IMAGE_TYPE, time_ns, msg)


def compressed_image(time_ns: int, pixels_bgr: np.ndarray, suffix: str = ".png") -> Message:
    ok, encoded = cv2.imencode(suffix, pixels_bgr)
    assert ok
    msg = _types()[COMPRESSED_TYPE](header=header(time_ns), format=suffix.lstrip("."),
                                    data=encoded.reshape(-1).astype(np.uint8))
    return Message(IMAGE_TOPIC, COMPRESSED_TYPE, time_ns, msg)


def write_bag(path: Path, messages: Sequence[Message], storage: str = "sqlite3") -> Path:
    """A rosbag2 folder of ``messages``, written by rosbags (each topic's connection made at its first message)."""
    store = typestore()
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin) as writer:
        connections: dict[str, Any] = {}
        for message in messages:
            if message.topic not in connections:
                connections[message.topic] = writer.add_connection(message.topic, message.msgtype, typestore=store)
            writer.write(connections[message.topic], message.time_ns,
                         store.serialize_cdr(message.msg, message.msgtype))
    return path


def read_topic(path: Path, topic: str) -> list[tuple[int, Any]]:
    """Every message of ``topic`` in a bag, deserialised by rosbags, with its bag time."""
    store = typestore()
    with Reader(path) as reader:
        connections = [c for c in reader.connections if c.topic == topic]
        return [(time_ns, store.deserialize_cdr(raw, connection.msgtype))
                for connection, time_ns, raw in reader.messages(connections=connections)]
