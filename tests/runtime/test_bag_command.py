"""``popcode bag`` (issue 64) with real bags written by rosbags (SQLite3 and MCAP): the poses it writes as
``vision_msgs/Detection3DArray`` and ``PoseArray`` are, frame by frame, the ones ``popcode predict --detector``
gives on the same pixels (the same ``FramePoseEstimator``), read back with rosbags' deserialiser and the MCAP
reader; and every bag it cannot use is refused in one line, exit 2, nothing written."""

from __future__ import annotations

import json
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from popcode_runtime import DetectedBox, FramePose, PoseEstimator, Prediction
from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.base.output_lock import OutputLock
from popcode_runtime.commands.cli import main
from popcode_runtime.geometry.rotations import quaternion_to_matrix, random_rotations
from popcode_runtime.ros.bag_input import MAX_WAITING
from popcode_runtime.ros.images import IMAGE_TYPE, depth_array, image_array
from popcode_runtime.ros.messages import DETECTIONS_TYPE, POSES_TYPE, detection_array, pose_message, typestore
from tools.paths import MODELS_DIR, SHIPPED_DETECTOR, SHIPPED_MODELS
from tools.ros_bags import (
    DEPTH_TOPIC,
    FRAME_ID,
    IMAGE_TOPIC,
    INFO_TOPIC,
    PERIOD_NS,
    SAMPLE_BIN_K,
    START_NS,
    Message,
    camera_info,
    compressed_image,
    image,
    read_topic,
    write_bag,
)

POSE_MODELS = [str(path) for path in SHIPPED_MODELS]
DETECTOR = str(SHIPPED_DETECTOR)
BIN = MODELS_DIR / "samples" / "bin.png"  # 720 x 540 grey; its camera is the README's
K_BIN = SAMPLE_BIN_K
DETECTIONS, POSES = "/popcode/detections", "/popcode/poses"
BLANK_SIZE = (320, 240)  # frames where the detector finds nothing: the tests of the bag's plumbing stay cheap
K_BLANK = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])
PLUMB_BOB = (-0.12, 0.05, 0.001, -0.002, 0.0)


def _bag_args(bag: Path, out: Path, *extra: str) -> list[str]:
    return ["bag", *POSE_MODELS, "--bag", str(bag), "--detector", DETECTOR, "--image-topic", IMAGE_TOPIC,
            "--camera-info-topic", INFO_TOPIC, "--out", str(out), "--quiet", *extra]


def _predict(picture: Path, capsys: pytest.CaptureFixture, *extra: str) -> list[dict]:
    """``popcode predict --detector`` on one picture file: the reference every frame of a bag is compared with."""
    capsys.readouterr()
    assert main(["predict", *POSE_MODELS, str(picture), "--detector", DETECTOR, "--K",
                 ",".join(str(v) for v in K_BIN[[0, 1, 0, 1], [0, 1, 2, 2]]), "--translation", "--json",
                 *extra]) == 0
    return json.loads(capsys.readouterr().out)["predictions"]


def _bin_frames() -> list[np.ndarray]:
    """Two frames of the bin: as recorded and mirrored left to right (K's principal point is the centre's)."""
    grey = cv2.imread(str(BIN), cv2.IMREAD_UNCHANGED)
    return [grey, np.ascontiguousarray(grey[:, ::-1])]


def _tinted(grey: np.ndarray) -> np.ndarray:
    """A BGR frame whose channels differ: a swapped channel order would give another grey frame."""
    return np.stack([grey * 0.7, grey * 0.85, grey], axis=-1).astype(np.uint8)


def _assert_same_poses(detections: list, poses: list, expected: list[dict]) -> None:
    """The Detection3D of one frame against ``popcode predict``'s JSON of the same pixels: same objects, scores
    and poses, in the same order (metres and quaternions converted back)."""
    assert len(detections) == len(poses) == len(expected) > 0
    for detection, pose, reference in zip(detections, poses, expected, strict=True):
        result = detection.results[0]
        assert result.hypothesis.class_id == str(reference["detection"]["obj_id"])
        confidence = 1.0 if reference["confidence"] is None else reference["confidence"]
        assert result.hypothesis.score == pytest.approx(reference["detection"]["score"] * confidence, abs=1e-12)
        for message in (result.pose.pose, pose):
            q = message.orientation
            np.testing.assert_allclose(quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w])), reference["R_m2c"],
                                       atol=1e-12)
            p = message.position
            np.testing.assert_allclose(np.array([p.x, p.y, p.z]) * 1000.0, reference["t_m2c_mm"], atol=1e-9)


@pytest.fixture(scope="module")
def pictures(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[Path]]:
    """The frames as picture files for ``popcode predict``: grey (8 and 16 bits), and tinted colour (BGR on
    disk)."""
    folder = tmp_path_factory.mktemp("frames")
    files: dict[str, list[Path]] = {"grey": [], "grey16": [], "colour": []}
    for index, grey in enumerate(_bin_frames()):
        for kind, pixels in (("grey", grey), ("grey16", grey.astype(np.uint16) * 257), ("colour", _tinted(grey))):
            files[kind].append(folder / f"{kind}{index}.png")
            cv2.imwrite(str(files[kind][-1]), pixels)
    return files


@pytest.fixture(scope="module")
def predicted() -> dict[Path, list[dict]]:
    """``popcode predict``'s estimates of each picture file, made once: the round trips of one kind share them."""
    return {}


@pytest.fixture(scope="module")
def shipped_objects() -> dict[int, dict]:
    """The shipped pose models' objects, by id, as their metadata holds them."""
    return {obj_id: info for path in POSE_MODELS for obj_id, info in PoseEstimator(path).metadata.objects.items()}


def _recorded(encoding: str, frames: list[np.ndarray]) -> list[Message]:
    """A camera's recording: its CameraInfo before each image, 10 frames a second."""
    messages = []
    for index, pixels in enumerate(frames):
        time_ns = START_NS + index * PERIOD_NS
        messages.append(camera_info(time_ns, K_BIN, (pixels.shape[1], pixels.shape[0])))
        if encoding == "png":
            messages.append(compressed_image(time_ns, pixels))
        else:  # the pictures are BGR, as OpenCV reads them
            messages.append(image(time_ns, np.ascontiguousarray(pixels[..., ::-1]) if encoding == "rgb8" else pixels,
                                  encoding))
    return messages


# (input storage, encoding on the image topic, pictures compared with, output storage)
ROUND_TRIPS = [("sqlite3", "mono8", "grey", "mcap"), ("mcap", "bgr8", "colour", "sqlite3"),
               ("sqlite3", "rgb8", "colour", "mcap"), ("mcap", "mono16", "grey16", "mcap"),
               ("mcap", "png", "colour", "mcap")]


@pytest.mark.parametrize("storage, encoding, kind, out_storage", ROUND_TRIPS,
                         ids=[f"{s}-{e}-to-{o}" for s, e, _, o in ROUND_TRIPS])
def test_the_bag_holds_the_poses_predict_gives_on_the_same_frames(
        storage: str, encoding: str, kind: str, out_storage: str, pictures: dict[str, list[Path]],
        predicted: dict[Path, list[dict]], shipped_objects: dict[int, dict], tmp_path: Path,
        capsys: pytest.CaptureFixture) -> None:
    frames = [cv2.imread(str(path), cv2.IMREAD_UNCHANGED) for path in pictures[kind]]
    bag = write_bag(tmp_path / "recorded", _recorded(encoding, frames), storage)
    out = tmp_path / "poses"
    assert main(_bag_args(bag, out, "--storage", out_storage)) == 0
    assert sorted(path.name for path in tmp_path.iterdir()) == ["poses", "recorded"]  # no temporary left
    detections, poses = read_topic(out, DETECTIONS), read_topic(out, POSES)
    assert [t for t, _ in detections] == [t for t, _ in poses] == [START_NS, START_NS + PERIOD_NS]
    for picture, (time_ns, array), (_, pose_array) in zip(pictures[kind], detections, poses, strict=True):
        assert array.header.frame_id == pose_array.header.frame_id == FRAME_ID
        assert array.header.stamp.sec * 10**9 + array.header.stamp.nanosec == time_ns
        assert all(d.header == array.header for d in array.detections)
        if picture not in predicted:
            predicted[picture] = _predict(picture, capsys)
        _assert_same_poses(array.detections, pose_array.poses, predicted[picture])
        for detection in array.detections:
            info = shipped_objects[int(detection.results[0].hypothesis.class_id)]
            size = detection.bbox.size
            assert [size.x, size.y, size.z] == pytest.approx([info[f"size_{a}"] / 1000.0 for a in "xyz"])


def test_the_mcap_output_reads_back_with_the_mcap_reader_without_warnings(tmp_path: Path) -> None:
    frames = [np.full(BLANK_SIZE[::-1], 90, np.uint8)] * 2
    messages = [m for i, f in enumerate(frames) for m in (camera_info(START_NS + i * PERIOD_NS, K_BLANK, BLANK_SIZE),
                                                           image(START_NS + i * PERIOD_NS, f, "mono8"))]
    out = tmp_path / "poses"
    assert main(_bag_args(write_bag(tmp_path / "recorded", messages), out)) == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with (out / "poses.mcap").open("rb") as stream:
            read = [(schema.name, schema.encoding, channel.topic, channel.message_encoding, message.log_time)
                    for schema, channel, message in make_reader(stream).iter_messages()]
    assert sorted(read) == sorted((name, "ros2msg", topic, "cdr", START_NS + i * PERIOD_NS) for i in range(2)
                                  for name, topic in ((DETECTIONS_TYPE, DETECTIONS), (POSES_TYPE, POSES)))
    assert [len(array.detections) for _, array in read_topic(out, DETECTIONS)] == [0, 0]  # every frame said


def test_depth_of_the_same_stamp_gives_predicts_depth_poses(pictures: dict[str, list[Path]], tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    grey = cv2.imread(str(pictures["grey"][0]), cv2.IMREAD_UNCHANGED)
    depth = np.full(grey.shape, 450, np.uint16)
    depth[:, :200] = 0  # no reading
    cv2.imwrite(str(tmp_path / "depth.png"), depth)
    # the depth camera's image after the colour one, and in metres
    metres = np.where(depth > 0, depth / 1000.0, np.nan).astype(np.float32)
    messages = [*_recorded("mono8", [grey]), image(START_NS, metres, "32FC1", DEPTH_TOPIC)]
    out = tmp_path / "poses"
    assert main(_bag_args(write_bag(tmp_path / "recorded", messages), out, "--depth-topic", DEPTH_TOPIC)) == 0
    [(_, array)], [(_, pose_array)] = read_topic(out, DETECTIONS), read_topic(out, POSES)
    expected = _predict(pictures["grey"][0], capsys, "--depth", str(tmp_path / "depth.png"), "--depth-scale", "1")
    assert {p["t_source"] for p in expected} >= {"depth"}
    _assert_same_poses(array.detections, pose_array.poses, expected)


def test_plumb_bob_distortion_is_undistorted_into_the_same_camera(pictures: dict[str, list[Path]], tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture) -> None:
    grey = cv2.imread(str(pictures["grey"][0]), cv2.IMREAD_UNCHANGED)
    messages = [camera_info(START_NS, K_BIN, (720, 540), d=PLUMB_BOB), image(START_NS, grey, "mono8")]
    out = tmp_path / "poses"
    assert main(_bag_args(write_bag(tmp_path / "recorded", messages), out)) == 0
    cv2.imwrite(str(tmp_path / "undistorted.png"), cv2.undistort(grey, K_BIN, np.array(PLUMB_BOB)))
    [(_, array)], [(_, pose_array)] = read_topic(out, DETECTIONS), read_topic(out, POSES)
    _assert_same_poses(array.detections, pose_array.poses, _predict(tmp_path / "undistorted.png", capsys))


def _blank_recording(count: int = 3, start_ns: int = START_NS) -> list[Message]:
    frame = np.full(BLANK_SIZE[::-1], 90, np.uint8)
    return [m for i in range(count) for m in (camera_info(start_ns + i * PERIOD_NS, K_BLANK, BLANK_SIZE),
                                              image(start_ns + i * PERIOD_NS, frame, "mono8"))]


@pytest.mark.parametrize("extra, times", [(["--every", "2"], [0, 2]), (["--start", "0.05"], [1, 2, 3]),
                                          (["--start", "0.05", "--end", "0.15"], [1])])
def test_every_nth_frame_and_a_time_range(extra: list[str], times: list[int], tmp_path: Path) -> None:
    out = tmp_path / "poses"
    assert main(_bag_args(write_bag(tmp_path / "recorded", _blank_recording(4)), out, *extra)) == 0
    assert [t for t, _ in read_topic(out, DETECTIONS)] == [START_NS + i * PERIOD_NS for i in times]


def test_overwrite_replaces_a_bag_and_leaves_nothing_else(tmp_path: Path) -> None:
    bag = write_bag(tmp_path / "recorded", _blank_recording(1))
    out = tmp_path / "poses"
    assert main(_bag_args(bag, out)) == 0
    assert main(_bag_args(bag, out, "--overwrite", "--every", "1", "--storage", "sqlite3")) == 0
    assert sorted(path.name for path in out.iterdir()) == ["metadata.yaml", "poses.db3"]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["poses", "recorded"]


def test_pose_messages_round_trip_millimetres_and_matrices() -> None:
    rotations = random_rotations(20, np.random.default_rng(64))
    for R, t_mm in zip(rotations, np.random.default_rng(65).uniform(-900, 900, (20, 3)), strict=True):
        pose = pose_message(R, t_mm)
        q = pose.orientation
        np.testing.assert_allclose(quaternion_to_matrix(np.array([q.x, q.y, q.z, q.w])), R, atol=1e-12)
        np.testing.assert_allclose([pose.position.x * 1000, pose.position.y * 1000, pose.position.z * 1000], t_mm,
                                   atol=1e-9)
        assert q.x**2 + q.y**2 + q.z**2 + q.w**2 == pytest.approx(1.0, abs=1e-12)


def _fields(message: object) -> object:
    """A message's fields as plain values, whichever classes built it (rosbags' dataclasses, namespaces)."""
    if isinstance(message, (list, tuple)):
        return [_fields(item) for item in message]
    if isinstance(message, np.ndarray):
        return message.tolist()
    names = [n for n in vars(message) if n not in ("__msgtype__", "msgtype")] if hasattr(message, "__dict__") else []
    return {n: _fields(getattr(message, n)) for n in names} if names else message


def test_a_node_builds_the_same_detections_from_its_own_message_classes() -> None:
    """What the rclpy node of docs/runtime.md does: the message classes looked up by name (``get_message`` there),
    here namespaces; the messages equal those written to a bag. The box lies centred on the object's box."""
    R = random_rotations(1, np.random.default_rng(7))[0]
    pose = FramePose(DetectedBox(3, (10.0, 20.0, 30.0, 40.0), 0.8),
                     Prediction(R, np.array([0.0, 0.0, 1.0]), 0.3, 0.9, (10.0, 20.0, 30.0, 40.0), 3,
                                t_m2c_mm=np.array([12.0, -30.0, 480.0]), confidence=0.5))
    info = {"min_x": -32.0, "size_x": 64.0, "min_y": -18.0, "size_y": 36.0, "min_z": -10.0, "size_z": 30.0}
    header = typestore().types["std_msgs/msg/Header"](
        stamp=typestore().types["builtin_interfaces/msg/Time"](sec=1, nanosec=2), frame_id=FRAME_ID)
    written = detection_array(header, [pose], {3: info})
    built = detection_array(header, [pose], {3: info}, lambda name: SimpleNamespace)
    assert _fields(built) == _fields(written)
    detection = written.detections[0]
    assert detection.results[0].hypothesis.score == pytest.approx(0.4)
    centre = detection.bbox.center.position
    expected = R @ np.array([0.0, 0.0, 5.0]) + [12.0, -30.0, 480.0]
    np.testing.assert_allclose(np.array([centre.x, centre.y, centre.z]) * 1000.0, expected, atol=1e-9)


def _info(**changes: object) -> list[Message]:
    """One blank frame after a CameraInfo with ``changes`` (keyword arguments of ``camera_info``)."""
    frame = np.full(BLANK_SIZE[::-1], 90, np.uint8)
    options = {"K": K_BLANK, "size": BLANK_SIZE, **changes}
    return [camera_info(START_NS, **options), image(START_NS, frame, "mono8")]


def _truncated(storage: str) -> Callable[[Path], Path]:
    """A bag whose one file lost its second half (a copy or a recording cut short)."""
    def make(folder: Path) -> Path:
        write_bag(folder, _blank_recording(3), storage)
        [data_file] = [path for path in folder.iterdir() if path.name != "metadata.yaml"]
        data = data_file.read_bytes()
        data_file.write_bytes(data[: len(data) // 2])
        return folder
    return make


def _not_a_bag(folder: Path) -> Path:
    folder.mkdir()
    (folder / "metadata.yaml").write_text("not: [a bag")
    return folder


def _picture(folder: Path) -> Path:
    cv2.imwrite(str(folder.with_suffix(".png")), np.zeros((4, 4), np.uint8))
    return folder.with_suffix(".png")


def _depth_of_another_stamp(folder: Path) -> Path:
    depth = image(START_NS + 1, np.full(BLANK_SIZE[::-1], 500, np.uint16), "16UC1", DEPTH_TOPIC)
    return write_bag(folder, [*_blank_recording(1), depth])


def _depth_of_another_camera(folder: Path) -> Path:
    """Depth images whose stamps never match the colour ones: the images waiting for theirs are bounded."""
    depth = np.full(BLANK_SIZE[::-1], 500, np.uint16)
    messages = [m for i in range(MAX_WAITING + 2) for m in (
        *_blank_recording(1, START_NS + i * PERIOD_NS), image(START_NS + i * PERIOD_NS + 1, depth, "16UC1",
                                                             DEPTH_TOPIC))]
    return write_bag(folder, messages)


# name -> (how the input is made in a folder, extra options, words of the one line)
HOSTILE = {
    "not a bag": (_not_a_bag, [], "as a ROS 2 bag"),
    "a picture": (_picture, [], "as a ROS 2 bag"),
    "missing topic": (lambda p: write_bag(p, _blank_recording(1)), ["--image-topic", "/camera/color"],
                      f"its topics: {INFO_TOPIC} (sensor_msgs/msg/CameraInfo), {IMAGE_TOPIC}"),
    "empty bag": (lambda p: write_bag(p, []), [], "its topics: none"),
    "image topic of CameraInfo": (lambda p: write_bag(p, _blank_recording(1)), ["--image-topic", INFO_TOPIC],
                                  "carries sensor_msgs/msg/CameraInfo"),
    "unknown encoding": (lambda p: write_bag(p, [_info()[0], image(START_NS, np.zeros((240, 160, 2), np.uint8),
                                                                   "yuv422")]), [], "encoding 'yuv422'"),
    "frame of another size": (lambda p: write_bag(p, _info(size=(640, 480), K=K_BIN)), [],
                              "is 320x240 but its CameraInfo is for 640x480"),
    "K off the image": (lambda p: write_bag(p, _info(K=np.array([[300.0, 0, 900], [0, 300, 119.5], [0, 0, 1]]))),
                        [], "principal point at (900, 119.5)"),
    "no CameraInfo before the frame": (lambda p: write_bag(p, _info()[::-1]), [],
                                       f"no CameraInfo on {INFO_TOPIC} before it"),
    "fisheye": (lambda p: write_bag(p, _info(model="equidistant", d=(0.1, 0.01, 0.0, 0.0))), [],
                "distortion model 'equidistant'"),
    "rolling shutter": (lambda p: write_bag(p, _info(model="rolling_shutter", d=(0.0,))), [],
                        "distortion model 'rolling_shutter'"),
    "CameraInfo of another frame": (lambda p: write_bag(p, _info(frame_id="left_optical")), [],
                                    "the CameraInfo before it on /camera/camera_info is of 'left_optical'"),
    "no images in the range": (lambda p: write_bag(p, _blank_recording(2)), ["--start", "5"],
                               "between --start and --end"),
    "depth of another stamp": (_depth_of_another_stamp, ["--depth-topic", DEPTH_TOPIC],
                               f"has no depth image of its header stamp on {DEPTH_TOPIC} before the bag's end"),
    "depth of another camera": (_depth_of_another_camera, ["--depth-topic", DEPTH_TOPIC],
                                f"within the {MAX_WAITING} images after it"),
    "truncated MCAP": (_truncated("mcap"), [], "cannot read"),
    "truncated SQLite3": (_truncated("sqlite3"), [], "database disk image is malformed"),
}


@pytest.mark.parametrize("case", HOSTILE)
def test_a_bag_it_cannot_use_is_one_line(case: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    make, extra, words = HOSTILE[case]
    bag = make(tmp_path / "recorded")
    before = sorted(path.name for path in tmp_path.iterdir())
    capsys.readouterr()
    assert main(_bag_args(bag, tmp_path / "poses", *extra)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("popcode: error: ") and words in err, err
    assert sorted(path.name for path in tmp_path.iterdir()) == before  # nothing written, no temporary left


@pytest.mark.parametrize("existing, extra, words", [
    ("bag", [], "exists already; pass --overwrite"),
    ("folder", ["--overwrite"], "is not a rosbag2 folder"),
    ("input", ["--overwrite"], "is the input"),
])
def test_an_output_it_must_not_replace_is_one_line(existing: str, extra: list[str], words: str, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture) -> None:
    bag = write_bag(tmp_path / "recorded", _blank_recording(1))
    out = {"bag": write_bag(tmp_path / "poses", []), "folder": tmp_path / "notes", "input": bag}[existing]
    if existing == "folder":
        out.mkdir()
        (out / "keep.txt").write_text("mine")
    capsys.readouterr()
    assert main(_bag_args(bag, out, *extra)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err, err
    assert existing != "folder" or (out / "keep.txt").read_text() == "mine"


def test_without_rosbags_the_command_says_what_to_install(tmp_path: Path, capsys: pytest.CaptureFixture,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rosbags.rosbag2", None)  # what an install without the extra finds
    assert main(_bag_args(tmp_path / "recorded", tmp_path / "poses")) == 2
    assert "pip install ./runtime[ros]" in capsys.readouterr().err


def test_image_messages_with_padded_rows_and_big_endian_pixels() -> None:
    """Rows longer than their pixels (``step``) and big-endian 16-bit data: the pixels as they are."""
    pixels = np.arange(5 * 7, dtype=np.uint16).reshape(5, 7) * 1000
    message = image(START_NS, pixels, "mono16").msg
    padded = np.zeros((5, 7 * 2 + 6), np.uint8)
    padded[:, :14] = pixels.astype(">u2").view(np.uint8).reshape(5, 14)
    message.data, message.step, message.is_bigendian = padded.reshape(-1), 20, 1
    np.testing.assert_array_equal(image_array(message, IMAGE_TYPE, "image"), pixels)
    message.data = message.data[:-1]  # one byte short of its last row
    with pytest.raises(PopcodeError, match="holds 99 bytes in rows of 20"):
        image_array(message, IMAGE_TYPE, "image")


def test_depth_in_metres_reads_as_millimetres_with_nan_as_no_reading() -> None:
    metres = np.array([[0.5, np.nan], [np.inf, 1.25]], np.float32)
    depth, scale = depth_array(image(START_NS, metres, "32FC1").msg, "depth")
    np.testing.assert_array_equal(depth * scale, [[500.0, 0.0], [0.0, 1250.0]])


def test_a_second_writer_of_the_same_out_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bag = write_bag(tmp_path / "recorded", _blank_recording(1))
    out = tmp_path / "poses"
    with OutputLock(tmp_path / "poses.lock", "held by the test"):  # what a running popcode bag holds
        capsys.readouterr()
        assert main(_bag_args(bag, out)) == 2
    assert "another popcode bag is writing" in capsys.readouterr().err and not out.exists()
    assert main(_bag_args(bag, out)) == 0  # released: the next run writes
