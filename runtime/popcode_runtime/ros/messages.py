"""popcode's estimates as ROS 2 messages: ``vision_msgs/msg/Detection3DArray`` and ``geometry_msgs/msg/PoseArray``.

Conventions (docs/design.md#robot-formats): the camera frame is ROS's optical frame,
which is OpenCV's, so ``R_m2c``/``t_m2c`` are the pose in the image's ``frame_id`` as they are; ROS carries
metres and quaternions ``(x, y, z, w)``, popcode millimetres and matrices, converted here and nowhere else.
A ``Detection3D`` per estimate: the image's header, ``results[0].hypothesis.class_id`` the object id as text,
``score`` the estimate's (detector score x calibrated confidence, as ``popcode run``), ``results[0].pose.pose``
the model-to-camera pose, ``bbox`` the object's 3-D box from its model info, centred at that pose.

The ``vision_msgs`` definitions are registered from their message text, as ROS 2 Humble's vision_msgs 4.x
defines them, in rosbags' Humble typestore (which has ``std_msgs``, ``geometry_msgs`` and ``sensor_msgs``). The
message classes are looked up by name (``message_class``), so a ROS node builds the same messages from rclpy's
classes (``rosidl_runtime_py.utilities.get_message``) as ``popcode bag`` writes with rosbags'.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from functools import cache
from typing import Any

import numpy as np

from ..geometry.rotations import matrix_to_quaternion
from ..inference.frame import FramePose
from .library import rosbags

MM_PER_M = 1000.0
DETECTIONS_TYPE = "vision_msgs/msg/Detection3DArray"
POSES_TYPE = "geometry_msgs/msg/PoseArray"
# vision_msgs 4.x (ROS 2 Humble), the fields as released; comments shortened.
VISION_MSGS = {
    "vision_msgs/msg/ObjectHypothesis": "# The unique ID of the object class.\nstring class_id\n"
                                        "# The probability or confidence value.\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": "vision_msgs/ObjectHypothesis hypothesis\n"
                                                "geometry_msgs/PoseWithCovariance pose\n",
    "vision_msgs/msg/BoundingBox3D": "# The 3D position and orientation of the bounding box center\n"
                                     "geometry_msgs/Pose center\n"
                                     "# The total size of the bounding box, in meters\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": "std_msgs/Header header\nObjectHypothesisWithPose[] results\n"
                                   "BoundingBox3D bbox\nstring id\n",
    DETECTIONS_TYPE: "std_msgs/Header header\nDetection3D[] detections\n",
}


@cache
def typestore() -> Any:
    """rosbags' ROS 2 Humble typestore with the ``vision_msgs`` types registered (one for the process)."""
    typesys = rosbags("typesys")
    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    for name, text in VISION_MSGS.items():
        store.register(typesys.get_types_from_msg(text, name))
    return store


MessageClass = Callable[[str], Any]  # "geometry_msgs/msg/Pose" -> its class, whose keywords are the fields


def rosbags_class(name: str) -> Any:
    """A message class of rosbags' typestore (:func:`typestore`)."""
    return typestore().types[name]


def pose_messages(R_m2c: np.ndarray, t_m2c_mm: np.ndarray, message_class: MessageClass = rosbags_class) -> list[Any]:
    """``geometry_msgs/msg/Pose`` of poses ``(N, 3, 3)``, ``(N, 3)`` [mm]: the translations in metres, the rotations as
    unit quaternions (computed in one call: a frame's parts cost one conversion, not one each)."""
    R = np.asarray(R_m2c, dtype=np.float64).reshape(-1, 3, 3)
    t_m = np.asarray(t_m2c_mm, dtype=np.float64).reshape(-1, 3) / MM_PER_M
    pose, point, quaternion = (message_class(f"geometry_msgs/msg/{name}") for name in ("Pose", "Point", "Quaternion"))
    return [pose(position=point(x=float(t[0]), y=float(t[1]), z=float(t[2])),
                 orientation=quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])))
            for t, q in zip(t_m, matrix_to_quaternion(R) if len(R) else np.zeros((0, 4)), strict=True)]


def pose_message(R_m2c: np.ndarray, t_m2c_mm: np.ndarray, message_class: MessageClass = rosbags_class) -> Any:
    """One pose's ``geometry_msgs/msg/Pose`` (:func:`pose_messages`)."""
    return pose_messages(R_m2c, t_m2c_mm, message_class)[0]


def box_centre_mm(R_m2c: np.ndarray, t_m2c_mm: np.ndarray, info: Mapping[str, Any]) -> np.ndarray:
    """The camera-frame centre [mm] of the object's 3-D box (``models_info``'s ``min_*``/``size_*`` [mm]) at the
    pose; the model's origin where they are missing."""
    low = np.array([float(info.get(f"min_{axis}", 0.0)) for axis in "xyz"])
    size = np.array([float(info.get(f"size_{axis}", 0.0)) for axis in "xyz"])
    return R_m2c @ (low + size / 2.0) + t_m2c_mm


def frame_arrays(poses: Sequence[FramePose], objects: Mapping[int, Mapping[str, Any]]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A frame's rotations ``(N, 3, 3)``, translations and box centres ``(N, 3)`` [mm], in the order of ``poses``."""
    R = np.array([p.prediction.R_m2c for p in poses], dtype=np.float64).reshape(-1, 3, 3)
    t_mm = np.array([p.prediction.t_m2c_mm for p in poses], dtype=np.float64).reshape(-1, 3)
    centres = np.array([box_centre_mm(p.prediction.R_m2c, p.prediction.t_m2c_mm, objects.get(p.detection.obj_id, {}))
                        for p in poses], dtype=np.float64).reshape(-1, 3)
    return R, t_mm, centres


def detection_array(header: Any, poses: Sequence[FramePose], objects: Mapping[int, Mapping[str, Any]],
                    message_class: MessageClass = rosbags_class) -> Any:
    """A ``Detection3DArray`` of a frame's poses (each with a translation), with the image's ``header``;
    ``objects``: the models' object infos by id (their boxes; a point where an info has none)."""
    R, t_mm, centres = frame_arrays(poses, objects)
    detections = []
    for pose, object_pose, centre in zip(poses, pose_messages(R, t_mm, message_class),
                                         pose_messages(R, centres, message_class), strict=True):
        hypothesis = message_class("vision_msgs/msg/ObjectHypothesis")(class_id=str(pose.detection.obj_id),
                                                                       score=float(pose.score))
        with_covariance = message_class("geometry_msgs/msg/PoseWithCovariance")(
            pose=object_pose, covariance=np.zeros(36, dtype=np.float64))  # not estimated
        result = message_class("vision_msgs/msg/ObjectHypothesisWithPose")(hypothesis=hypothesis, pose=with_covariance)
        info = objects.get(pose.detection.obj_id, {})
        x, y, z = (float(info.get(f"size_{axis}", 0.0)) / MM_PER_M for axis in "xyz")
        size = message_class("geometry_msgs/msg/Vector3")(x=x, y=y, z=z)
        box = message_class("vision_msgs/msg/BoundingBox3D")(center=centre, size=size)
        detections.append(message_class("vision_msgs/msg/Detection3D")(header=header, results=[result], bbox=box,
                                                                       id=""))
    return message_class(DETECTIONS_TYPE)(header=header, detections=detections)


def pose_array(header: Any, poses: Sequence[FramePose], message_class: MessageClass = rosbags_class) -> Any:
    """A ``PoseArray`` of a frame's poses, in the order of its ``Detection3DArray``."""
    R, t_mm, _ = frame_arrays(poses, {})
    return message_class(POSES_TYPE)(header=header, poses=pose_messages(R, t_mm, message_class))
