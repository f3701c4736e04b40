"""The one per-image loop: each image read once, each box predicted by its object's model, errors name the image."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx_models import linear_model, save
from symmetry_cases import CASES

import popcode_runtime.inference.image_loop as image_loop
from popcode_runtime import PopcodeError, PoseEstimator, read_image
from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.geometry.rotations import random_rotations
from popcode_runtime.inference.image_loop import ImageBoxes, estimate_images, group_by_image
from popcode_runtime.model.metadata import ModelMetadata, Representation

LAYOUT = CodeLayout(n_axes=162, n_angles=12)
K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 120.0], [0.0, 0.0, 1.0]])


def _model(path: Path, obj_ids: list[int], seed: int) -> PoseEstimator:
    """A real ONNX model of ``obj_ids`` whose code peaks at its own random rotation (input-dependent a little)."""
    bias = PopulationCode(LAYOUT).encode(random_rotations(1, np.random.default_rng(seed))[0])
    meta = ModelMetadata(representation=Representation.POPULATION_CODE, code=LAYOUT,
                         objects={obj_id: CASES["none"] for obj_id in obj_ids}, training={"dataset": "unit-test"})
    return PoseEstimator(save(linear_model(bias, weight_scale=0.05, metadata=meta, seed=seed), path))


@pytest.fixture
def models(tmp_path: Path) -> list[PoseEstimator]:
    return [_model(tmp_path / "a.onnx", [1, 2], 1), _model(tmp_path / "b.onnx", [3], 2)]


@pytest.fixture
def images(tmp_path: Path) -> list[Path]:
    rng = np.random.default_rng(0)
    paths = [tmp_path / f"{index}.png" for index in range(3)]
    for path in paths:
        cv2.imwrite(str(path), rng.integers(0, 256, (240, 320), np.uint8))
    return paths


BOXES = [(10.0, 20.0, 60.0, 50.0), (100.0, 40.0, 80.0, 90.0), (200.0, 100.0, 70.0, 70.0), (30.0, 150.0, 50.0, 60.0)]


def test_each_box_gets_the_prediction_of_its_objects_model(models: list[PoseEstimator], images: list[Path],
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    reads: list[Path] = []
    monkeypatch.setattr(image_loop, "read_image", lambda path: reads.append(path) or read_image(path))
    obj_ids = [3, 1, 3, 2]  # the models' objects interleaved
    work = [ImageBoxes(("image", index), path, K, BOXES, obj_ids) for index, path in enumerate(images)]
    done = list(estimate_images(models, ["a", "b"], work))
    assert reads == images  # each image read once, in the given order
    assert [d.key for d in done] == [("image", 0), ("image", 1), ("image", 2)]
    for result, path in zip(done, images, strict=True):
        image = read_image(path)
        np.testing.assert_array_equal(result.image, image)
        assert [p.obj_id for p in result.predictions] == obj_ids and [p.box for p in result.predictions] == BOXES
        for box, obj_id, prediction in zip(BOXES, obj_ids, result.predictions, strict=True):
            model = models[0] if obj_id in (1, 2) else models[1]
            direct = model.predict(image, [box], K=K, obj_ids=[obj_id])[0]
            np.testing.assert_allclose(prediction.R_m2c, direct.R_m2c, atol=1e-9)
        assert [(estimator, [p.obj_id for p in found]) for estimator, found in result.by_model] == \
            [(models[0], [1, 2]), (models[1], [3, 3])]  # model order, each model's boxes in box order
        assert result.predict_s > 0 and result.seconds >= result.predict_s
    models_differ = done[0].predictions[0].R_m2c - done[0].predictions[1].R_m2c
    assert np.abs(models_differ).max() > 0.1  # the routing matters: the two models disagree


def test_a_model_without_boxes_is_not_called_and_predict_options_pass_through(models: list[PoseEstimator],
                                                                              images: list[Path]) -> None:
    [result] = estimate_images(models, ["a", "b"], [ImageBoxes(0, images[0], None, BOXES[:2], [2, 1])],
                               return_code=True)
    assert [estimator for estimator, _ in result.by_model] == [models[0]]
    assert all(p.code is not None and p.code.shape == (models[0].metadata.output_dim,) for p in result.predictions)


def test_an_object_in_two_models_is_refused_before_any_image(models: list[PoseEstimator], tmp_path: Path) -> None:
    twin = _model(tmp_path / "c.onnx", [3, 4], 3)
    missing = ImageBoxes(0, tmp_path / "never-read.png", K, BOXES[:1], [3])
    with pytest.raises(PopcodeError, match=r"object 3 is in both b and c; give one model per object"):
        next(estimate_images([*models, twin], ["a", "b", "c"], [missing]))


def test_an_error_of_one_image_names_it(models: list[PoseEstimator], images: list[Path], tmp_path: Path) -> None:
    outside = [ImageBoxes(0, images[0], K, BOXES, [1, 2, 3, 1]), ImageBoxes(1, images[1], K, [(2000, 0, 10, 10)], [3])]
    loop = estimate_images(models, ["a", "b"], outside)
    assert next(loop).key == 0  # the images before the bad one are done
    with pytest.raises(PopcodeError, match=rf"^{images[1]}: .*wholly outside"):
        next(loop)
    unknown = [ImageBoxes(0, images[2], K, BOXES[:1], [9])]
    with pytest.raises(PopcodeError, match=rf"^{images[2]}: no model knows objects \[9\] \(the models know \[1, 2, 3"):
        next(estimate_images(models, ["a", "b"], unknown))
    absent = tmp_path / "absent.png"
    with pytest.raises(PopcodeError, match=rf"^image file not found: {absent}$"):  # named once, not twice
        next(estimate_images(models, ["a", "b"], [ImageBoxes(0, absent, K, BOXES[:1], [1])]))
    with pytest.raises(PopcodeError, match="2 object ids for 1 boxes"):
        ImageBoxes(0, images[0], K, BOXES[:1], [1, 2])


class _Row:
    def __init__(self, image_path: Path, K: np.ndarray, box: tuple[float, ...], obj_id: int) -> None:
        self.image_path, self.K, self.box, self.obj_id = image_path, K, box, obj_id


def test_group_by_image_keys_each_image_by_its_rows(images: list[Path]) -> None:
    rows = [_Row(images[1], K, BOXES[0], 1), _Row(images[0], 2 * K, BOXES[1], 3), _Row(images[1], 3 * K, BOXES[2], 2)]
    grouped = group_by_image(rows)
    assert [(g.key, g.path, list(g.boxes), list(g.obj_ids)) for g in grouped] == \
        [((0, 2), images[1], [BOXES[0], BOXES[2]], [1, 2]), ((1,), images[0], [BOXES[1]], [3])]
    np.testing.assert_array_equal(grouped[0].K, K)  # an image's camera is its first row's
