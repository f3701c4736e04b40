"""Issue 50: a camera matrix is checked against the image it comes with; a crop of a larger frame says where it lies.

An allocentric model's rotation goes through the ray of the box centre, so another image's ``K`` turned it
silently (28 deg with a 720x540 camera's K on a 128x128 sample, 90 deg with ``cx = 5000``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from hostile_cases import LAYOUT, OBJECT, run_cli
from onnx_models import linear_model, save

from popcode_runtime import ModelMetadata, PopcodeError, PopulationCode, PoseEstimator, Representation, RotationFrame
from popcode_runtime.geometry.camera import (
    MAX_FIELD_OF_VIEW_DEG,
    MIN_FIELD_OF_VIEW_DEG,
    camera_for_image,
    parse_camera_matrix,
)
from popcode_runtime.geometry.rotations import random_rotations

MODELS = Path(__file__).resolve().parents[2] / "models"
# Full frames of the BOP datasets' test cameras, rounded: (width, height), (fx, fy, cx, cy)
BOP_CAMERAS = {
    "lm": ((640, 480), (572.4, 573.6, 325.3, 242.0)),
    "tless-primesense": ((720, 540), (1075.7, 1073.9, 373.1, 255.7)),
    "ycbv": ((640, 480), (1066.8, 1067.5, 313.0, 241.3)),
    "itodd": ((1280, 960), (2992.6, 2992.6, 633.1, 444.3)),
    "hope": ((1920, 1080), (1390.5, 1387.0, 965.0, 522.6)),
    "tudl": ((640, 480), (515.0, 515.0, 321.6, 214.1)),
}
FRAME_K = [1075.65, 1073.90, 360.0, 270.0]
FRAME_SHAPE = (540, 720)
ORIGIN = (400, 250)  # the crop's top-left in the frame
CROP_SHAPE = (220, 260)
BOX = [450.0, 300.0, 120.0, 100.0]  # in the frame; its crop square lies inside the crop


@pytest.fixture(scope="module")
def allocentric_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A model whose code depends on the crop's pixels (so a crop that sees other pixels answers otherwise)."""
    bias = PopulationCode(LAYOUT).encode(random_rotations(1, np.random.default_rng(50))[0])
    metadata = ModelMetadata(representation=Representation.POPULATION_CODE, code=LAYOUT, objects={7: OBJECT},
                             rotation_frame=RotationFrame.ALLOCENTRIC)
    return save(linear_model(bias, weight_scale=0.5, metadata=metadata), tmp_path_factory.mktemp("m") / "allo.onnx")


def _frame() -> np.ndarray:
    return np.random.default_rng(7).integers(0, 256, size=FRAME_SHAPE, dtype=np.uint8)


def _crop(frame: np.ndarray) -> np.ndarray:
    return frame[ORIGIN[1] : ORIGIN[1] + CROP_SHAPE[0], ORIGIN[0] : ORIGIN[0] + CROP_SHAPE[1]].copy()


def _in_crop(box: list[float]) -> list[float]:
    return [box[0] - ORIGIN[0], box[1] - ORIGIN[1], box[2], box[3]]


@pytest.mark.parametrize("name", sorted(BOP_CAMERAS))
def test_the_full_frames_of_bop_cameras_pass_unchanged(name: str) -> None:
    (width, height), camera = BOP_CAMERAS[name]
    K = parse_camera_matrix(camera)
    assert camera_for_image(K, (height, width)) is K


def test_the_shipped_samples_pass() -> None:
    for sample in json.loads((MODELS / "samples" / "samples.json").read_text())["samples"]:
        image = cv2.imread(str(MODELS / "samples" / sample["image"]), cv2.IMREAD_UNCHANGED)
        camera_for_image(parse_camera_matrix(sample["K"]), image.shape)


@pytest.mark.parametrize(("fov_deg", "fits"), [(MIN_FIELD_OF_VIEW_DEG * 0.99, False),
                                               (MIN_FIELD_OF_VIEW_DEG * 1.01, True),
                                               (MAX_FIELD_OF_VIEW_DEG - 0.1, True),
                                               (MAX_FIELD_OF_VIEW_DEG + 0.1, False)])
def test_the_field_of_view_bounds(fov_deg: float, fits: bool) -> None:
    focal = 320.0 / math.tan(math.radians(fov_deg) / 2)  # across 640 px, the principal point in the middle
    K = parse_camera_matrix([focal, focal * 0.75, 320.0, 240.0])  # the same angle across 480 px
    if fits:
        camera_for_image(K, (480, 640))
    else:
        with pytest.raises(PopcodeError, match="a camera sees 0.5 to 170 deg"):
            camera_for_image(K, (480, 640))


@pytest.mark.parametrize("camera", [[864, 864, 359.5, 269.5], [153.6, 153.6, 5000.0, 63.5],
                                    [153.6, 153.6, 63.5, -1.0], [1.0, 1.0, 63.5, 63.5], [1e5, 1e5, 63.5, 63.5]])
def test_an_allocentric_model_refuses_a_camera_that_is_not_the_images(allocentric_model: Path,
                                                                    camera: list[float]) -> None:
    """The issue's variants on a 128x128 image: another camera's K, cx = 5000, a negative cy, fx of 1 and 1e5."""
    image = np.zeros((128, 128), np.uint8)
    estimator = PoseEstimator(allocentric_model, threads=1)
    estimator.predict(image, [[20, 19, 84, 92]], K=[153.6, 153.6, 63.5, 63.5])  # the image's own camera
    with pytest.raises(PopcodeError, match="principal point|a camera sees"):
        estimator.predict(image, [[20, 19, 84, 92]], K=camera)


def test_a_crop_with_its_origin_gives_the_frames_rotation_and_translation(allocentric_model: Path) -> None:
    estimator, frame = PoseEstimator(allocentric_model, threads=1), _frame()
    whole = estimator.predict(frame, [BOX], K=FRAME_K, translation=True)[0]
    cut = estimator.predict(_crop(frame), [_in_crop(BOX)], K=FRAME_K, translation=True, crop_origin=ORIGIN)[0]
    np.testing.assert_allclose(cut.R_m2c, whole.R_m2c, atol=1e-12)
    np.testing.assert_allclose(cut.t_m2c_mm, whole.t_m2c_mm, atol=1e-6)  # mm
    with pytest.raises(PopcodeError, match=r"principal point at \(360, 270\), outside the 260x220 image"):
        estimator.predict(_crop(frame), [_in_crop(BOX)], K=FRAME_K)
    shifted = parse_camera_matrix([FRAME_K[0], FRAME_K[1], FRAME_K[2] - ORIGIN[0], FRAME_K[3] - ORIGIN[1]])
    np.testing.assert_allclose(camera_for_image(parse_camera_matrix(FRAME_K), CROP_SHAPE, ORIGIN), shifted)


def test_popcode_predict_crop_origin(allocentric_model: Path, tmp_path: Path) -> None:
    frame = _frame()
    cv2.imwrite(str(tmp_path / "frame.png"), frame)
    cv2.imwrite(str(tmp_path / "crop.png"), _crop(frame))
    camera = ",".join(f"{v:g}" for v in FRAME_K)

    def rotation(image: str, box: list[float], *options: str) -> list:
        code, out, err = run_cli(["predict", str(allocentric_model), str(tmp_path / image), "--box",
                                  ",".join(f"{v:g}" for v in box), "--K", camera, "--json", *options])
        assert code == 0, err
        return json.loads(out)["predictions"][0]["R_m2c"]

    whole = rotation("frame.png", BOX)
    origin = f"{ORIGIN[0]},{ORIGIN[1]}"
    np.testing.assert_allclose(rotation("crop.png", _in_crop(BOX), "--crop-origin", origin,
                                        "--draw", str(tmp_path / "drawn.png")), whole, atol=1e-12)
    assert cv2.imread(str(tmp_path / "drawn.png")).shape[:2] == CROP_SHAPE
    code, _, err = run_cli(["predict", str(allocentric_model), str(tmp_path / "crop.png"), "--box", "50,50,120,100",
                            "--K", camera])
    assert code == 2 and "outside the 260x220 image" in err


def test_popcode_run_refuses_a_cam_K_of_another_image_size_before_any_work(tmp_path: Path) -> None:
    scene = tmp_path / "split" / "000001"
    (scene / "gray").mkdir(parents=True)
    cv2.imwrite(str(scene / "gray" / "000000.png"), np.zeros((128, 128), np.uint8))
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": [1075.65, 0, 360, 0, 1073.9, 270, 0, 0,
                                                                         1]}}))
    (scene / "scene_gt.json").write_text(json.dumps({"0": [{"cam_R_m2c": np.eye(3).ravel().tolist(),
                                                            "cam_t_m2c": [0, 0, 500], "obj_id": 1}]}))
    (scene / "scene_gt_info.json").write_text(json.dumps({"0": [{"bbox_obj": [20, 20, 60, 60], "visib_fract": 1}]}))
    out = tmp_path / "results.csv"
    code, _, err = run_cli(["run", str(MODELS / "builtin-parts-1-2.onnx"), "--split", str(tmp_path / "split"),
                            "--gt-boxes", "--out", str(out), "--quiet"])
    assert code == 2 and "scene 1 image 0 (000000.png), its cam_K in scene_camera.json" in err, err
    assert "outside the 128x128 image" in err and sorted(tmp_path.iterdir()) == [tmp_path / "split"]
