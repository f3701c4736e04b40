"""``popcode bag --foxglove`` (issue 64, deliver 2): the Foxglove MCAP of a bag's frames, read back with the
``mcap`` reader and decoded with the schemas it carries (protobuf, built from the file's own descriptors): each
frame's image and camera as popcode saw them, and every part's box at the pose the output bag holds."""

from __future__ import annotations

import base64
import contextlib
import json
import struct
import warnings
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from websockets.sync.client import connect

from popcode_runtime import DetectedBox, FramePose, Prediction
from popcode_runtime.commands.cli import main
from popcode_runtime.geometry.rotations import random_rotations
from popcode_runtime.ros.bag_input import CameraFrame
from popcode_runtime.ros.foxglove_scene import CALIBRATION_TOPIC, SCENE_TOPIC, serve_scene
from popcode_runtime.ros.foxglove_scene import IMAGE_TOPIC as VIEW_IMAGE
from popcode_runtime.ros.messages import detection_array
from tools.paths import MODELS_DIR, SHIPPED_DETECTOR, SHIPPED_MODELS
from tools.ros_bags import (
    FRAME_ID,
    IMAGE_TOPIC,
    INFO_TOPIC,
    PERIOD_NS,
    SAMPLE_BIN_K,
    START_NS,
    camera_info,
    header,
    image,
    read_topic,
    write_bag,
)

POSE_MODELS = [str(path) for path in SHIPPED_MODELS]
DETECTOR = str(SHIPPED_DETECTOR)
K_BIN = SAMPLE_BIN_K
PLUMB_BOB = (-0.12, 0.05, 0.001, -0.002, 0.0)


def _message_class(name: str, descriptors: bytes) -> Any:
    """The protobuf class of schema ``name`` built from its serialised ``FileDescriptorSet`` alone."""
    pool = descriptor_pool.DescriptorPool()
    for file in descriptor_pb2.FileDescriptorSet.FromString(descriptors).file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def _decoded(path: Path) -> dict[str, list[tuple[int, Any]]]:
    """Every message of a Foxglove MCAP by topic, decoded by the protobuf schema the file carries for it; warnings
    are errors."""
    classes: dict[int, Any] = {}
    found: dict[str, list[tuple[int, Any]]] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with path.open("rb") as stream:
            for schema, channel, message in make_reader(stream).iter_messages():
                assert schema.encoding == channel.message_encoding == "protobuf"
                if schema.id not in classes:
                    classes[schema.id] = _message_class(schema.name, schema.data)
                found.setdefault(channel.topic, []).append((message.log_time, classes[schema.id].FromString(
                    message.data)))
    return found


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list[np.ndarray]]:
    """A two-frame bag of the bin (the second mirrored) through ``popcode bag --foxglove``; its camera has
    plumb_bob distortion, so the file shows the undistorted frames."""
    folder = tmp_path_factory.mktemp("foxglove")
    grey = cv2.imread(str(MODELS_DIR / "samples" / "bin.png"), cv2.IMREAD_UNCHANGED)
    frames = [grey, np.ascontiguousarray(grey[:, ::-1])]
    messages = [m for i, f in enumerate(frames) for m in (
        camera_info(START_NS + i * PERIOD_NS, K_BIN, (720, 540), d=PLUMB_BOB),
        image(START_NS + i * PERIOD_NS, f, "mono8"))]
    bag = write_bag(folder / "recorded", messages)
    out, view = folder / "poses", folder / "view.mcap"
    assert main(["bag", *POSE_MODELS, "--bag", str(bag), "--detector", DETECTOR, "--image-topic", IMAGE_TOPIC,
                 "--camera-info-topic", INFO_TOPIC, "--out", str(out), "--foxglove", str(view), "--quiet"]) == 0
    return out, view, frames


def test_the_file_holds_each_frame_and_its_camera(run: tuple[Path, Path, list[np.ndarray]]) -> None:
    _, view, frames = run
    decoded = _decoded(view)
    assert sorted(decoded) == sorted([VIEW_IMAGE, CALIBRATION_TOPIC, SCENE_TOPIC])
    times = [START_NS + i * PERIOD_NS for i in range(len(frames))]
    for topic in decoded:
        assert [t for t, _ in decoded[topic]] == times
    for (_, raw), (_, calibration), grey in zip(decoded[VIEW_IMAGE], decoded[CALIBRATION_TOPIC], frames, strict=True):
        assert (raw.frame_id, raw.encoding, raw.width, raw.height) == (FRAME_ID, "mono8", 720, 540)
        pixels = np.frombuffer(raw.data, np.uint8).reshape(540, raw.step)[:, :720]
        np.testing.assert_array_equal(pixels, cv2.undistort(grey, K_BIN, np.array(PLUMB_BOB)))
        assert list(calibration.K) == K_BIN.reshape(9).tolist() and calibration.distortion_model == ""
        assert (calibration.frame_id, calibration.width, calibration.height) == (FRAME_ID, 720, 540)


def test_every_part_is_drawn_at_the_pose_of_the_bag(run: tuple[Path, Path, list[np.ndarray]]) -> None:
    out, view, _ = run
    scenes = _decoded(view)[SCENE_TOPIC]
    arrays = read_topic(out, "/popcode/detections")
    assert len(scenes) == len(arrays) == 2
    for (_, scene), (_, array) in zip(scenes, arrays, strict=True):
        assert [d.type for d in scene.deletions] == [1]  # ALL: the last frame's parts go
        assert len(scene.entities) == len(array.detections) > 0
        for entity, detection in zip(scene.entities, array.detections, strict=True):
            assert entity.frame_id == FRAME_ID and entity.frame_locked
            assert {kv.key: kv.value for kv in entity.metadata} == {
                "object": detection.results[0].hypothesis.class_id}
            [cube] = entity.cubes
            box = detection.bbox
            for got, want in ((cube.pose.position, box.center.position), (cube.pose.orientation,
                                                                           box.center.orientation),
                              (cube.size, box.size)):
                assert [getattr(got, a) for a in "xyz"] == pytest.approx([getattr(want, a) for a in "xyz"],
                                                                         abs=1e-12)
            [axes] = entity.lines
            pose = detection.results[0].pose.pose
            assert [axes.pose.position.x, axes.pose.position.y, axes.pose.position.z] == pytest.approx(
                [pose.position.x, pose.position.y, pose.position.z], abs=1e-12)
            assert len(axes.points) == len(axes.colors) == 6


def test_a_foxglove_file_that_exists_is_refused_without_overwrite(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    view = tmp_path / "view.mcap"
    view.write_bytes(b"mine")
    frame = np.full((240, 320), 90, np.uint8)
    bag = write_bag(tmp_path / "recorded", [camera_info(START_NS, np.array([[300.0, 0, 159.5], [0, 300, 119.5],
                                                                            [0, 0, 1]]), (320, 240)),
                                             image(START_NS, frame, "mono8")])
    capsys.readouterr()
    assert main(["bag", *POSE_MODELS, "--bag", str(bag), "--detector", DETECTOR, "--image-topic", IMAGE_TOPIC,
                 "--camera-info-topic", INFO_TOPIC, "--out", str(tmp_path / "poses"), "--foxglove", str(view)]) == 2
    assert "--foxglove" in capsys.readouterr().err and view.read_bytes() == b"mine"
    assert not (tmp_path / "poses").exists()


def test_a_run_that_fails_midway_leaves_neither_file(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """The first frame is written to both outputs before the second is refused: neither appears, no temporary
    stays."""
    K = np.array([[300.0, 0, 159.5], [0, 300, 119.5], [0, 0, 1]])
    messages = [camera_info(START_NS, K, (320, 240)), image(START_NS, np.full((240, 320), 90, np.uint8), "mono8"),
                image(START_NS + PERIOD_NS, np.full((200, 320), 90, np.uint8), "mono8")]
    bag = write_bag(tmp_path / "recorded", messages)
    capsys.readouterr()
    assert main(["bag", *POSE_MODELS, "--bag", str(bag), "--detector", DETECTOR, "--image-topic", IMAGE_TOPIC,
                 "--camera-info-topic", INFO_TOPIC, "--out", str(tmp_path / "poses"), "--foxglove",
                 str(tmp_path / "view.mcap"), "--quiet"]) == 2
    assert "image 1 on /camera/image_raw" in capsys.readouterr().err
    assert sorted(path.name for path in tmp_path.iterdir()) == ["recorded"]


def test_the_live_server_sends_the_scene_to_a_client_on_the_loopback_address() -> None:
    """``serve_scene`` for a live camera: a WebSocket client (Foxglove's protocol, subprotocol foxglove.sdk.v1)
    subscribes to what the server advertises and receives the frame's image, camera and parts, decoded by the
    advertised schemas: the part's box where the Detection3D puts it."""
    R = random_rotations(1, np.random.default_rng(11))[0]
    pose = FramePose(DetectedBox(3, (10.0, 20.0, 30.0, 40.0), 0.8),
                     Prediction(R, np.array([0.0, 0.0, 1.0]), 0.3, 0.9, (10.0, 20.0, 30.0, 40.0), 3,
                                t_m2c_mm=np.array([12.0, -30.0, 480.0])))
    objects = {3: {"min_x": -32.0, "size_x": 64.0, "min_y": -18.0, "size_y": 36.0, "min_z": -10.0, "size_z": 30.0}}
    frame = CameraFrame(0, START_NS, header(START_NS), np.full((6, 8), 7, np.uint8),
                        np.array([[5.0, 0.0, 3.5], [0.0, 5.0, 2.5], [0.0, 0.0, 1.0]]))
    scene, server = serve_scene(objects, port=0)
    try:
        with connect(f"ws://127.0.0.1:{server.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=30) as client:
            advertised = {}
            while len(advertised) < 3:
                message = json.loads(client.recv(timeout=30))
                if message["op"] == "advertise":
                    advertised.update({channel["id"]: channel for channel in message["channels"]})
            client.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid}
                                                                          for cid in advertised]}))
            received: dict[str, Any] = {}
            for _ in range(300):  # the subscription takes effect a moment after it is sent: log until it has
                scene.add(frame, [pose])
                with contextlib.suppress(TimeoutError):
                    while len(received) < 3:
                        data = client.recv(timeout=0.1)
                        opcode, cid, log_time = struct.unpack_from("<BIQ", data)
                        assert opcode == 1 and log_time == START_NS
                        channel = advertised[cid]
                        decoder = _message_class(channel["schemaName"], base64.b64decode(channel["schema"]))
                        received[channel["topic"]] = decoder.FromString(data[13:])
                if len(received) == 3:
                    break
    finally:
        server.stop()
    assert received[VIEW_IMAGE].data == bytes([7] * 48) and received[VIEW_IMAGE].encoding == "mono8"
    assert list(received[CALIBRATION_TOPIC].K) == frame.K.reshape(9).tolist()
    [entity] = received[SCENE_TOPIC].entities
    centre = detection_array(frame.header, [pose], objects).detections[0].bbox.center.position
    assert [entity.cubes[0].pose.position.x, entity.cubes[0].pose.position.y, entity.cubes[0].pose.position.z] == \
        pytest.approx([centre.x, centre.y, centre.z], abs=1e-12)
