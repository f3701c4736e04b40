"""The picture in 3-D: frames and poses as Foxglove shows them, in an MCAP file (``popcode bag --foxglove``) or
live from Foxglove's WebSocket server (:func:`serve_scene`, for a camera).

Per frame, at the image's bag time, in the image's ``frame_id`` (the camera's optical frame; ``camera`` where
the image names none), with the Foxglove SDK's own schemas:

- ``/popcode/image``: the frame as popcode saw it (``foxglove.RawImage``; undistorted where its camera was);
- ``/popcode/calibration``: its camera (``foxglove.CameraCalibration``: K, no distortion left), so the 3-D panel
  draws the frustum and the image panel can overlay the scene;
- ``/popcode/scene``: a ``foxglove.SceneUpdate`` that first deletes the previous frame's entities, then one entity
  per part: its 3-D box at the estimated pose (translucent magenta, as ``--draw`` draws the hull), its axes (model
  x, y, z in red, green, blue) and a label with the object id and score.

The file is written with :func:`~popcode_runtime.base.files.atomic_path`: whole at the end or not at all. Each
sink has a Foxglove context of its own, so nothing goes to the SDK's global one.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np

from ..base.errors import library_step
from ..base.files import atomic_path
from ..inference.frame import FramePose
from .bag_input import CameraFrame
from .library import optional_module
from .messages import MM_PER_M, frame_arrays, pose_messages

IMAGE_TOPIC, CALIBRATION_TOPIC, SCENE_TOPIC = "/popcode/image", "/popcode/calibration", "/popcode/scene"
DEFAULT_FRAME = "camera"
BOX_RGBA = (1.0, 0.0, 1.0, 0.35)
AXIS_RGBA = ((1.0, 0.0, 0.0, 1.0), (0.0, 1.0, 0.0, 1.0), (0.0, 0.0, 1.0, 1.0))  # model x, y, z
AXIS_SHARE = 0.6  # of the object's longest box side: the drawn axes' length
LABEL_RGBA = (1.0, 1.0, 1.0, 1.0)
LOOPBACK, DEFAULT_PORT = "127.0.0.1", 8765  # Foxglove's own default port
RAW_ENCODINGS = {(np.dtype(np.uint8), 2): "mono8", (np.dtype(np.uint16), 2): "mono16", (np.dtype(np.uint8), 3): "rgb8"}


def _vector(kind: Any, values_m: np.ndarray) -> Any:
    """A Foxglove ``Vector3`` or ``Point3`` of three numbers [m]."""
    x, y, z = (float(v) for v in values_m)
    return kind(x=x, y=y, z=z)


def _poses(messages: Any, R: np.ndarray, t_mm: np.ndarray) -> list[Any]:
    """Foxglove ``Pose`` messages: :func:`~popcode_runtime.ros.messages.pose_messages` with Foxglove's classes, the
    one conversion of millimetres and matrices."""
    classes = {"geometry_msgs/msg/Pose": messages.Pose, "geometry_msgs/msg/Point": messages.Vector3,
               "geometry_msgs/msg/Quaternion": messages.Quaternion}
    return pose_messages(R, t_mm, classes.__getitem__)


def _colour(messages: Any, rgba: Sequence[float]) -> Any:
    return messages.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _entities(messages: Any, poses: Sequence[FramePose], objects: Mapping[int, Mapping[str, Any]], stamp: Any,
              frame_id: str) -> list[Any]:
    """One entity a part: its box, axes and label."""
    R, t_mm, centres = frame_arrays(poses, objects)
    identity = np.broadcast_to(np.eye(3), R.shape)
    entities = []
    for index, (pose, box_pose, axes_pose, label_pose) in enumerate(zip(
            poses, _poses(messages, R, centres), _poses(messages, R, t_mm), _poses(messages, identity, centres),
            strict=True)):
        info = objects.get(pose.detection.obj_id, {})
        size_mm = np.array([float(info.get(f"size_{axis}", 0.0)) for axis in "xyz"])
        cube = messages.CubePrimitive(pose=box_pose, size=_vector(messages.Vector3, size_mm / MM_PER_M),
                                      color=_colour(messages, BOX_RGBA))
        length_m = AXIS_SHARE * max(size_mm.max(), 1.0) / MM_PER_M
        origin = _vector(messages.Point3, np.zeros(3))
        ends = [_vector(messages.Point3, length_m * np.eye(3)[axis]) for axis in range(3)]
        axes = messages.LinePrimitive(type=messages.LinePrimitiveLineType.LineList, pose=axes_pose, thickness=3.0,
                                      scale_invariant=True, points=[point for end in ends for point in (origin, end)],
                                      colors=[_colour(messages, rgba) for rgba in AXIS_RGBA for _ in range(2)])
        label = messages.TextPrimitive(pose=label_pose, billboard=True, font_size=14.0, scale_invariant=True,
                                       color=_colour(messages, LABEL_RGBA),
                                       text=f"object {pose.detection.obj_id} ({pose.score:.2f})")
        entities.append(messages.SceneEntity(
            timestamp=stamp, frame_id=frame_id, id=f"part {index}", frame_locked=True,
            metadata=[messages.KeyValuePair(key="object", value=str(pose.detection.obj_id))], cubes=[cube],
            lines=[axes], texts=[label]))
    return entities


class FoxgloveScene:
    """The three channels of a frame's image, camera and parts on a Foxglove context: :meth:`add` logs one frame
    to whatever that context's sinks are (an MCAP file, :class:`FoxgloveOutput`; a WebSocket server,
    :func:`serve_scene`)."""

    def __init__(self, objects: Mapping[int, Mapping[str, Any]], context: Any) -> None:
        channels, self.messages = optional_module("foxglove.channels"), optional_module("foxglove.messages")
        self.objects, self.context = objects, context  # the context is kept: its channels close with it
        self.image = channels.RawImageChannel(IMAGE_TOPIC, context=context)
        self.calibration = channels.CameraCalibrationChannel(CALIBRATION_TOPIC, context=context)
        self.scene = channels.SceneUpdateChannel(SCENE_TOPIC, context=context)

    def add(self, frame: CameraFrame, poses: Sequence[FramePose]) -> None:
        """One frame: its image, its camera and its parts (at ``frame.time_ns``, in its header's frame)."""
        messages = self.messages
        stamp = messages.Timestamp(sec=int(frame.header.stamp.sec), nsec=int(frame.header.stamp.nanosec))
        frame_id = str(frame.header.frame_id) or DEFAULT_FRAME
        pixels = np.ascontiguousarray(frame.image)
        height, width = pixels.shape[:2]
        self.image.log(messages.RawImage(timestamp=stamp, frame_id=frame_id, width=width, height=height,
                                         encoding=RAW_ENCODINGS[pixels.dtype, pixels.ndim],
                                         step=pixels.strides[0], data=pixels.tobytes()),
                       log_time=frame.time_ns)
        K = np.asarray(frame.K, dtype=np.float64)
        P = np.hstack([K, np.zeros((3, 1))])
        self.calibration.log(messages.CameraCalibration(timestamp=stamp, frame_id=frame_id, width=width, height=height,
                                                        distortion_model="", D=[], K=K.reshape(9).tolist(),
                                                        R=np.eye(3).reshape(9).tolist(), P=P.reshape(12).tolist()),
                             log_time=frame.time_ns)
        clear = messages.SceneEntityDeletion(timestamp=stamp, type=messages.SceneEntityDeletionType.All)
        entities = _entities(messages, poses, self.objects, stamp, frame_id)
        self.scene.log(messages.SceneUpdate(deletions=[clear], entities=entities), log_time=frame.time_ns)


class FoxgloveOutput:
    """The Foxglove MCAP of a run: a :class:`FoxgloveScene` writing into a file while the block runs; closed and
    renamed into place when it ends without an error, removed when it ends with one."""

    def __init__(self, path: Path, objects: Mapping[int, Mapping[str, Any]]) -> None:
        self.path, self.objects = path, objects

    def __enter__(self) -> FoxgloveScene:
        foxglove = optional_module("foxglove")
        self._stack = ExitStack()
        try:
            temporary = self._stack.enter_context(atomic_path(self.path))
            context = foxglove.Context()  # its own: nothing goes to the process's global sinks
            with library_step(f"write {self.path} (Foxglove MCAP)"):
                self._writer = foxglove.open_mcap(temporary, context=context)
            self._stack.callback(self._close)
            return FoxgloveScene(self.objects, context)
        except BaseException:
            self._stack.__exit__(*sys.exc_info())
            raise

    def _close(self) -> None:
        with library_step(f"write {self.path} (Foxglove MCAP)"):
            self._writer.close()

    def __exit__(self, *exc_info: Any) -> None:
        self._stack.__exit__(*exc_info)


def serve_scene(objects: Mapping[int, Mapping[str, Any]], host: str = LOOPBACK, port: int = DEFAULT_PORT
                ) -> tuple[FoxgloveScene, Any]:
    """A live view: a :class:`FoxgloveScene` whose frames go to Foxglove's WebSocket server on ``host:port``
    (Foxglove connects to ``ws://host:port``; port 0 takes a free one, ``server.port`` says which). The loopback
    address by default: serving every interface is the caller's choice. Stop it with ``server.stop()``."""
    foxglove = optional_module("foxglove")
    context = foxglove.Context()
    with library_step(f"start Foxglove's WebSocket server on {host}:{port}"):
        server = foxglove.start_server(name="popcode", host=host, port=port, context=context)
    return FoxgloveScene(objects, context), server
