"""Camera frames out of a rosbag2 (SQLite3 or MCAP), streamed: each image with the ``CameraInfo`` received
before it and, when asked, the depth image of the same header stamp.

A bag of any size is read one message at a time: an image is decoded only when it is one popcode estimates
(every n-th, inside the time range), and at most :data:`MAX_WAITING` images wait for their depth (a depth
camera publishes its image beside the colour one, either first), so memory does not grow with the bag.
Everything a bag can hold wrong is one line naming the topic and the image: not a bag, a topic missing (the
topics that exist are listed) or of another type, an image popcode cannot read, no ``CameraInfo`` before a
frame, a ``CameraInfo`` of another size or frame, a truncated file.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..base.errors import PopcodeError, library_step
from .images import (
    CAMERA_INFO_TYPE,
    COMPRESSED_TYPE,
    IMAGE_TYPE,
    Camera,
    camera_from_info,
    check_frame_size,
    depth_array,
    image_array,
)
from .library import rosbags
from .messages import typestore

MAX_WAITING = 32  # images (or depth images) waiting for their partner of the same stamp
NS_PER_S = 1_000_000_000


@dataclass(frozen=True)
class Topics:
    """The topics a run reads; ``depth`` optional."""

    image: str
    camera_info: str
    depth: str | None = None


@dataclass(frozen=True)
class CameraFrame:
    """One camera frame: its number on the image topic (from 0), the bag's time of it [ns], the image's header
    (stamp and ``frame_id``, for the messages about it), the image as popcode takes it, its camera and depth."""

    index: int
    time_ns: int
    header: Any
    image: np.ndarray
    K: np.ndarray
    depth: np.ndarray | None = None
    depth_scale: float = 1.0  # mm per depth unit


@contextmanager
def open_bag(path: Path) -> Iterator[Any]:
    """An open ``rosbags`` reader of the bag at ``path`` (a rosbag2 folder, or one ``.mcap``/``.db3`` file)."""
    rosbag2 = rosbags("rosbag2")
    if not path.exists():
        raise PopcodeError(f"bag {path} does not exist")
    with library_step(f"read {path} as a ROS 2 bag (a rosbag2 folder, .mcap or .db3)"):
        reader = rosbag2.Reader(path)
        reader.open()
    try:
        yield reader
    finally:
        reader.close()


def _connections(reader: Any, topic: str, types: tuple[str, ...], option: str) -> list[Any]:
    """The bag's connections of ``topic``, refused where it is missing or of another message type."""
    found = [c for c in reader.connections if c.topic == topic]
    if not found:
        topics = ", ".join(f"{name} ({info.msgtype})" for name, info in sorted(reader.topics.items())) or "none"
        raise PopcodeError(f"{option} {topic} is not in the bag; its topics: {topics}")
    wrong = sorted({c.msgtype for c in found} - set(types))
    if wrong:
        raise PopcodeError(f"{option} {topic} carries {wrong[0]}; it must be {' or '.join(types)}")
    return found


class BagFrames:
    """The frames of a bag's image topic, checked against its topics when made."""

    def __init__(self, reader: Any, topics: Topics, path: Path) -> None:
        self.reader, self.topics, self.path = reader, topics, path
        self.images = _connections(reader, topics.image, (IMAGE_TYPE, COMPRESSED_TYPE), "--image-topic")
        self.infos = _connections(reader, topics.camera_info, (CAMERA_INFO_TYPE,), "--camera-info-topic")
        self.depths = [] if topics.depth is None else _connections(reader, topics.depth, (IMAGE_TYPE,),
                                                                   "--depth-topic")
        self._camera: Camera | None = None
        self._camera_info: tuple[Any, ...] = ()
        self._camera_frame = ""

    @property
    def image_count(self) -> int:
        return sum(c.msgcount for c in self.images)

    def _messages(self, stop_ns: int | None) -> Iterator[tuple[Any, int, bytes]]:
        """The bag's messages of the three topics in time order; a failure of the file is one line."""
        messages = self.reader.messages(connections=[*self.images, *self.infos, *self.depths], stop=stop_ns)
        while True:
            with library_step(f"read bag {self.path} (a truncated or damaged file?)"):
                message = next(messages, None)
            if message is None:
                return
            yield message

    def _deserialize(self, raw: bytes, msgtype: str, what: str) -> Any:
        with library_step(f"read {what}"):
            return typestore().deserialize_cdr(raw, msgtype)

    def _update_camera(self, info: Any, where: str) -> None:
        """The camera of a new ``CameraInfo``; the undistortion of an unchanged one is not computed again."""
        key = (int(info.width), int(info.height), str(info.distortion_model), tuple(np.asarray(info.k).tolist()),
               tuple(np.asarray(info.d).tolist()))
        if key != self._camera_info:
            self._camera, self._camera_info = camera_from_info(info, where), key
        self._camera_frame = str(info.header.frame_id)

    def frames(self, every: int = 1, start_s: float = 0.0, end_s: float | None = None) -> Iterator[CameraFrame]:
        """Every ``every``-th image from ``start_s`` to ``end_s`` seconds after the bag's start, with its camera
        (and depth); ``CameraInfo`` is read from the bag's start, so a frame's camera may come before ``start_s``."""
        first = self.reader.start_time
        start_ns = first + round(start_s * NS_PER_S)
        stop_ns = None if end_s is None else first + round(end_s * NS_PER_S)
        image_types = {c.id: c.msgtype for c in self.images}
        depth_ids = {c.id for c in self.depths}
        waiting: OrderedDict[tuple[int, int], tuple[int, int, Any, np.ndarray, Camera]] = OrderedDict()
        depths: OrderedDict[tuple[int, int], Any] = OrderedDict()
        index = -1
        for connection, time_ns, raw in self._messages(stop_ns):
            if connection.msgtype == CAMERA_INFO_TYPE:
                self._update_camera(self._deserialize(raw, CAMERA_INFO_TYPE, f"a CameraInfo on {connection.topic}"),
                                    f"the CameraInfo on {connection.topic} at {time_ns} ns")
                continue
            if connection.id in depth_ids:
                depth = self._deserialize(raw, IMAGE_TYPE, f"a depth image on {connection.topic}")
                stamp = (int(depth.header.stamp.sec), int(depth.header.stamp.nanosec))
                if stamp in waiting:
                    yield self._frame(*waiting.pop(stamp), depth)
                else:  # its image comes later, or is one not estimated (every n-th, before the start)
                    depths[stamp] = depth
                    if len(depths) > MAX_WAITING:
                        depths.popitem(last=False)
                continue
            index += 1
            if index % every or time_ns < start_ns:
                continue
            where = f"image {index} on {connection.topic} ({time_ns} ns)"
            msg = self._deserialize(raw, image_types[connection.id], where)
            if self._camera is None:
                raise PopcodeError(f"{where} has no CameraInfo on {self.topics.camera_info} before it: popcode "
                                   "needs the camera of each frame (record the camera_info topic with the images)")
            self._check_frame_id(msg, where)
            image = image_array(msg, image_types[connection.id], where)
            check_frame_size(self._camera, image, where)
            stamp = (int(msg.header.stamp.sec), int(msg.header.stamp.nanosec))
            if not self.depths:
                yield self._frame(index, time_ns, msg.header, image, self._camera, None)
            elif stamp in depths:
                yield self._frame(index, time_ns, msg.header, image, self._camera, depths.pop(stamp))
            else:
                waiting[stamp] = (index, time_ns, msg.header, image, self._camera)
                if len(waiting) > MAX_WAITING:
                    self._refuse_no_depth(waiting, f"within the {MAX_WAITING} images after it")
        if waiting:
            self._refuse_no_depth(waiting, "before the bag's end")

    def _check_frame_id(self, msg: Any, where: str) -> None:
        frame_id, camera_frame = str(msg.header.frame_id), self._camera_frame
        if frame_id and camera_frame and frame_id != camera_frame:
            raise PopcodeError(f"{where} is in frame {frame_id!r} but the CameraInfo before it on "
                               f"{self.topics.camera_info} is of {camera_frame!r}: another camera's")

    def _refuse_no_depth(self, waiting: OrderedDict, when: str) -> None:
        """The first image still waiting for its depth (at the bag's end, or once :data:`MAX_WAITING` wait)."""
        index, time_ns = next(iter(waiting.values()))[:2]
        raise PopcodeError(f"image {index} on {self.topics.image} ({time_ns} ns) has no depth image of its header "
                           f"stamp on {self.topics.depth} {when}: are the two topics one registered camera?")

    def _frame(self, index: int, time_ns: int, header: Any, image: np.ndarray, camera: Camera,
               depth_msg: Any | None) -> CameraFrame:
        """The frame popcode estimates: image (and depth) undistorted into the camera's K."""
        if depth_msg is None:
            return CameraFrame(index, time_ns, header, camera.undistort(image), camera.K)
        where = f"the depth image of image {index} on {self.topics.depth}"
        depth, scale = depth_array(depth_msg, where)
        check_frame_size(camera, depth, where)
        return CameraFrame(index, time_ns, header, camera.undistort(image), camera.K,
                        camera.undistort(depth, nearest=True), scale)
