"""The picture of each estimate: axes where the camera projects them, the hull outline, the same picture for every
symmetric-equivalent pose, an honest label, and ``popcode predict --draw``."""

from __future__ import annotations

import json
import re
from pathlib import Path

import cv2
import numpy as np
import pytest
from symmetry_cases import BASE, CASES

from popcode_runtime import CodeLayout, ModelMetadata, PopcodeError, PoseEstimator, Representation, read_image
from popcode_runtime.commands.cli import main
from popcode_runtime.commands.drawing import (
    AXIS_COLOURS_BGR,
    AXIS_LENGTH_OF_BOX,
    BOX_COLOUR_BGR,
    HULL_COLOUR_BGR,
    axis_glyphs,
    draw_predictions,
    estimate_label,
)
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, matrix_to_axis_angle, rotvec_to_matrix
from popcode_runtime.geometry.symmetries import continuous_axis, discrete_transforms
from popcode_runtime.inference.prediction import Prediction

MODELS = Path(__file__).resolve().parents[2] / "models"
SAMPLES = json.loads((MODELS / "samples" / "samples.json").read_text())["samples"]
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
BLANK = np.full((480, 640), 128, np.uint8)
ROTVEC = np.array([0.4, -0.7, 0.25])  # a pose whose three axis ends fall on distinct, well separated pixels
T_MM = np.array([15.0, -10.0, 500.0])
BOX = (250.0, 170.0, 140.0, 120.0)
HULL_MM = np.array([[x, y, z] for x in (-40, 40) for y in (-25, 25) for z in (-15, 15)], dtype=float)


def metadata(objects: dict[int, dict]) -> ModelMetadata:
    axis_only = any("symmetries_continuous" in info for info in objects.values())
    layout = CodeLayout(n_axes=42, n_angles=1 if axis_only else 12, axis_only=axis_only,
                        symmetry_axis=(0.0, 0.0, 1.0))
    return ModelMetadata(representation=Representation.POPULATION_CODE, code=layout, objects=objects)


def prediction(R: np.ndarray, obj_id: int = 1, t_mm: np.ndarray | None = None, box=BOX,
               confidence: float | None = None, score: float = 0.734) -> Prediction:
    axis, angle = matrix_to_axis_angle(R)
    return Prediction(R_m2c=R, axis=axis, angle_rad=float(angle), score=score, box=box, obj_id=obj_id,
                      t_m2c_mm=t_mm, confidence=confidence)


def projected_px(points_mm: np.ndarray, R: np.ndarray, t_mm: np.ndarray) -> np.ndarray:
    """Pixels of model points, by OpenCV's own projection (not the runtime's)."""
    rvec, _ = cv2.Rodrigues(R)
    pixels, _ = cv2.projectPoints(points_mm.reshape(-1, 1, 3), rvec, t_mm.reshape(3, 1), K, None)
    return np.round(pixels.reshape(-1, 2)).astype(int)


def test_axis_ends_have_the_axis_colours_and_far_pixels_are_untouched() -> None:
    R = rotvec_to_matrix(ROTVEC)
    picture = draw_predictions(BLANK, [prediction(R, t_mm=T_MM)], metadata({1: {}}), K)
    assert picture.shape == (480, 640, 3) and picture.dtype == np.uint8
    length_mm = AXIS_LENGTH_OF_BOX * max(BOX[2:]) * T_MM[2] / K[0, 0]
    ends = projected_px(length_mm * np.eye(3), R, T_MM)
    centre = projected_px(np.zeros(3), R, T_MM)[0]
    assert len({tuple(e) for e in ends}) == 3 and np.linalg.norm(ends - centre, axis=1).min() > 20
    for (u, v), colour in zip(ends, AXIS_COLOURS_BGR, strict=True):
        assert picture[v, u].tolist() == colour.tolist(), f"axis end ({u}, {v})"
    x, y, w, h = BOX
    assert picture[int(y), int(x)].tolist() == list(BOX_COLOUR_BGR)  # the box's corner
    right = int(max(x + w, ends[:, 0].max())) + 10
    below = int(max(y + h, ends[:, 1].max())) + 10
    left = int(min(x, ends[:, 0].min())) - 10
    above = int(min(y, ends[:, 1].min())) - 10
    # the label's band lies above the box's top-left corner, as wide as its widest line in the picture's font size
    scale = float(np.clip(min(picture.shape[:2]) / 900, 0.3, 1.2))
    label_right = int(x) + max(cv2.getTextSize(line, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0][0]
                               for line in estimate_label(prediction(R, t_mm=T_MM))) + 10
    untouched = [picture[:, :left], picture[below:], picture[int(y):, right:],
                 picture[:above, max(right, label_right):]]
    assert all((part == 128).all() for part in untouched)
    assert (picture != 128).any(axis=2).sum() > 300  # something was drawn


def test_hull_outline_passes_through_the_projected_hull_vertices() -> None:
    R = rotvec_to_matrix(ROTVEC)
    info = {"hull_points_mm": HULL_MM.tolist()}
    picture = draw_predictions(BLANK, [prediction(R, t_mm=T_MM)], metadata({1: info}), K)
    vertices = cv2.convexHull(projected_px(HULL_MM, R, T_MM).astype(np.int32)).reshape(-1, 2)
    assert len(vertices) >= 4
    for u, v in vertices:
        assert picture[v, u].tolist() == list(HULL_COLOUR_BGR), f"hull vertex ({u}, {v})"
    without_translation = draw_predictions(BLANK, [prediction(R)], metadata({1: info}), K)
    assert not (without_translation == np.array(HULL_COLOUR_BGR)).all(axis=2).any()  # no pose, no outline


def test_without_translation_the_axes_start_at_the_box_centre() -> None:
    R = rotvec_to_matrix(ROTVEC)
    picture = draw_predictions(BLANK, [prediction(R)], metadata({1: {}}))
    x, y, w, h = BOX
    centre = np.array([x + w / 2, y + h / 2])
    ends = np.round(centre + AXIS_LENGTH_OF_BOX * max(w, h) * R.T[:, :2]).astype(int)  # orthographic
    for (u, v), colour in zip(ends, AXIS_COLOURS_BGR, strict=True):
        assert picture[v, u].tolist() == colour.tolist()


SHIFTED_TWO_FOLD = {**BASE, "symmetries_discrete": [
    [-1.0, 0.0, 0.0, 20.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]]}  # about z through x = 10
SHIFTED_CONTINUOUS = {**BASE, "symmetries_continuous": [{"axis": [0, 1, 1], "offset": [5.0, 0.0, -8.0]}]}


def equivalent_poses(info: dict, R: np.ndarray, t_mm: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(R·S, t + R·t_S)`` for every symmetry (continuous ones at a few angles): the same object in the image."""
    discrete = discrete_transforms(info)
    poses = [(R @ S, t_mm + R @ t) for S, t in zip(discrete.R, discrete.t_mm, strict=True)]
    if "symmetries_continuous" in info:
        axis = continuous_axis(info)
        offset = np.asarray(info["symmetries_continuous"][0]["offset"], float)
        for angle in (0.37, 2.0, np.pi):
            C = axis_angle_to_matrix(axis, angle)
            poses += [(R_eq @ C, t_eq + R_eq @ (offset - C @ offset)) for R_eq, t_eq in poses[:len(discrete.R)]]
    return poses


def shipped_objects() -> dict[int, dict]:
    objects = {}
    for model in ("builtin-parts-1-2.onnx", "builtin-parts-3-6.onnx"):
        objects.update(PoseEstimator(MODELS / model).metadata.objects)
    return objects


@pytest.mark.parametrize("name", ["shipped 1", "shipped 2", "shipped 3", "shipped 4", "shipped 5", "two_fold",
                                  "four_fold", "continuous", "continuous_flip", "shifted two_fold",
                                  "shifted continuous"])
@pytest.mark.parametrize("with_translation", [True, False])
def test_the_picture_is_the_same_for_every_equivalent_pose(name: str, with_translation: bool) -> None:
    if name.startswith("shipped"):
        info = shipped_objects()[int(name.split()[1])]
    else:
        info = {"shifted two_fold": SHIFTED_TWO_FOLD, "shifted continuous": SHIFTED_CONTINUOUS}.get(name) or CASES[name]
    meta = metadata({1: info})
    R = rotvec_to_matrix(ROTVEC)
    poses = equivalent_poses(info, R, T_MM)
    assert len(poses) >= 2
    pictures = [draw_predictions(BLANK, [prediction(R_eq, t_mm=t_eq if with_translation else None)], meta, K)
                for R_eq, t_eq in poses]
    for index, picture in enumerate(pictures[1:], start=1):
        differing = (picture != pictures[0]).any(axis=2).sum()
        assert differing == 0, f"equivalent pose {index} changes {differing} pixels"


@pytest.mark.parametrize("with_translation", [True, False])
def test_poses_that_are_not_equivalent_give_different_pictures(with_translation: bool) -> None:
    """The control of the test above: a half turn that is no symmetry of the part changes the picture."""
    R = rotvec_to_matrix(ROTVEC)
    half_turn_z, half_turn_x = axis_angle_to_matrix(np.array([0.0, 0, 1]), np.pi), axis_angle_to_matrix(
        np.array([1.0, 0, 0]), np.pi)
    for info, turn in ((CASES["none"], half_turn_z), (CASES["two_fold"], half_turn_x),
                       (CASES["continuous"], half_turn_x), (CASES["four_fold"], half_turn_x)):
        t_mm = T_MM if with_translation else None
        first, second = (draw_predictions(BLANK, [prediction(pose, t_mm=t_mm)], metadata({1: info}), K)
                         for pose in (R, R @ turn))
        assert (first != second).any(axis=2).sum() > 20


def test_symmetric_axes_are_drawn_as_the_symmetries_allow() -> None:
    glyphs = {name: axis_glyphs(CASES[name]) for name in CASES}
    assert [(len(g.directions_m), g.arrow) for g in glyphs["none"]] == [(1, True)] * 3
    assert [(len(g.directions_m), g.arrow) for g in glyphs["two_fold"]] == [(2, False), (2, False), (1, True)]
    assert [(len(g.directions_m), g.arrow, g.colour_bgr) for g in glyphs["four_fold"]] == [
        (4, False, (0, 255, 255)), (1, True, (255, 0, 0))]  # x and y exchanged: one set, yellow
    assert [(len(g.directions_m), g.arrow) for g in glyphs["continuous"]] == [(1, True)]
    assert [(len(g.directions_m), g.arrow) for g in glyphs["continuous_flip"]] == [(2, False)]


def test_the_label_never_invents_a_confidence() -> None:
    R = np.eye(3)
    uncalibrated = estimate_label(prediction(R, obj_id=3, score=0.734))
    assert "no calibrated confidence" in " ".join(uncalibrated)
    assert re.findall(r"\d+(?:\.\d+)?", " ".join(uncalibrated)) == ["3", "0.73"]  # the id and the score, nothing else
    calibrated = estimate_label(prediction(R, obj_id=3, confidence=0.873))
    assert "confidence 0.87" in " ".join(calibrated) and "no calibrated" not in " ".join(calibrated)
    assert estimate_label(prediction(R, obj_id=None))[0].startswith("obj ?")
    meta = metadata({3: {}})
    pictures = [draw_predictions(BLANK, [prediction(R, obj_id=3, confidence=c)], meta) for c in (None, 0.2, 0.9)]
    assert (pictures[0] != pictures[1]).any() and (pictures[1] != pictures[2]).any()


def test_images_of_every_kind_become_bgr_and_translation_needs_k() -> None:
    rgb = np.random.default_rng(0).integers(0, 256, size=(20, 30, 3), dtype=np.uint8)
    meta = metadata({1: {}})
    np.testing.assert_array_equal(draw_predictions(rgb, [], meta), rgb[..., ::-1])
    np.testing.assert_array_equal(draw_predictions(rgb.astype(np.uint16) * 257, [], meta), rgb[..., ::-1])
    np.testing.assert_array_equal(draw_predictions(rgb / 255.0, [], meta), rgb[..., ::-1])
    grey = draw_predictions(rgb[..., 0], [], meta)
    assert grey.shape == (20, 30, 3) and (grey == rgb[..., :1]).all()
    with pytest.raises(PopcodeError, match="camera matrix K"):
        draw_predictions(BLANK, [prediction(np.eye(3), t_mm=T_MM)], meta)


@pytest.mark.parametrize("bad, problem", [(dict(R=np.full((3, 3), np.nan)), "R_m2c contains NaN"),
                                          (dict(box=(1.0, 2.0, np.inf, 4.0)), "box contains NaN or inf"),
                                          (dict(t_mm=np.array([0.0, 1.0])), r"t_m2c_mm must have shape \(3\)"),
                                          (dict(obj_id=9), "object 9 is not in this model")])
def test_a_bad_prediction_is_one_line(bad: dict, problem: str) -> None:
    arguments = {"R": np.eye(3), **bad}
    with pytest.raises(PopcodeError, match=problem):
        draw_predictions(BLANK, [prediction(arguments.pop("R"), **arguments)], metadata({1: {}}), K)
    with pytest.raises(PopcodeError, match="Prediction objects"):
        draw_predictions(BLANK, [{"R_m2c": np.eye(3)}], metadata({1: {}}), K)


def sample_arguments(index: int) -> tuple[Path, list[str]]:
    sample = SAMPLES[index]
    model = MODELS / ("builtin-parts-1-2.onnx" if sample["obj_id"] <= 2 else "builtin-parts-3-6.onnx")
    return model, [str(MODELS / "samples" / sample["image"]), "--box", ",".join(map(str, sample["box"])),
                   "--K", ",".join(map(str, sample["K"])), "--obj-id", str(sample["obj_id"]), "--translation"]


@pytest.mark.parametrize("index", [0, 2])
def test_predict_draw_writes_the_picture_of_the_estimates(tmp_path: Path, index: int, capsys) -> None:
    model, arguments = sample_arguments(index)
    out = tmp_path / "estimate.png"
    assert main(["predict", str(model), *arguments, "--draw", str(out), "--json"]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["estimate.png"]  # nothing half-written left beside it
    picture = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    image = read_image(arguments[0])
    assert picture.shape == (*image.shape, 3)
    printed = json.loads(capsys.readouterr().out)["predictions"]
    estimator = PoseEstimator(model)
    predictions = [prediction(np.array(p["R_m2c"]), obj_id=p["obj_id"], t_mm=np.array(p["t_m2c_mm"]),
                              box=tuple(p["box"]), score=p["score"], confidence=p["confidence"]) for p in printed]
    np.testing.assert_array_equal(picture, draw_predictions(image, predictions, estimator.metadata,
                                                            SAMPLES[index]["K"]))
    assert (picture.max(axis=2) != picture.min(axis=2)).sum() > 100  # coloured lines on a grey image


def test_an_existing_picture_is_replaced_only_with_overwrite(tmp_path: Path, capsys) -> None:
    model, arguments = sample_arguments(0)
    out = tmp_path / "estimate.png"
    out.write_bytes(b"an older picture")
    assert main(["predict", str(model), *arguments, "--draw", str(out)]) == 2
    assert "exists already; pass --overwrite" in capsys.readouterr().err and out.read_bytes() == b"an older picture"
    assert main(["predict", str(model), *arguments, "--draw", str(out), "--overwrite"]) == 0
    assert cv2.imread(str(out)).shape[:2] == read_image(arguments[0]).shape[:2]


@pytest.mark.parametrize("draw, problem", [("missing-folder/out.png", "does not exist"),
                                           ("out.xyz", "unknown image format"),
                                           ("out", "unknown image format"),
                                           (".", "is a folder")])
def test_a_bad_draw_path_is_one_line_before_the_model_runs(tmp_path: Path, draw: str, problem: str,
                                                           capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _, arguments = sample_arguments(2)
    # The model does not exist either: the --draw check must come first to be the error reported.
    assert main(["predict", str(tmp_path / "no-model.onnx"), *arguments, "--draw", draw]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("popcode: error: --draw") and problem in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.parametrize("t_mm", [[1e7, -1e7, 1e-3], [0.0, 0.0, -500.0], [0.0, 0.0, 1e-9]])
@pytest.mark.parametrize("name", ["none", "continuous"])
def test_degenerate_poses_draw_without_failing(t_mm: list[float], name: str) -> None:
    """Far off, behind the camera, at the pinhole: clipped to what OpenCV's integer pixels hold, or left out."""
    info = {**CASES[name], "hull_points_mm": HULL_MM.tolist()}
    huge_box = (-1e4, -1e4, 4e4, 4e4)
    for box in (BOX, huge_box):
        picture = draw_predictions(BLANK, [prediction(rotvec_to_matrix(ROTVEC), t_mm=np.array(t_mm), box=box)],
                                   metadata({1: info}), K)
        assert picture.shape == (480, 640, 3)
