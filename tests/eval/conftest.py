"""Fixtures shared by the evaluation tests: a few cluttered scenes and a population code that follows its crops."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from onnx_models import linear_model, save
from scene_fixtures import SCENE_OBJECTS, SCENE_SIZE, scene_objects

from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.data.scene_render import render_cluttered_test_split


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three cluttered images of parts 3 and 6, two or three parts each, repeats and border-cut boxes included."""
    return render_cluttered_test_split(tmp_path_factory.mktemp("scenes"), scenes=3, size=SCENE_SIZE,
                                       obj_ids=SCENE_OBJECTS, parts=(2, 3))


@pytest.fixture(scope="module")
def code_model(scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A population code without a calibrator whose peak the crop's pixels move: another box, another rotation."""
    layout = CodeLayout(n_axes=162, n_angles=12, sigma_deg=30.0)
    meta = ModelMetadata(Representation.POPULATION_CODE, layout, scene_objects(scenes))
    bias = PopulationCode(layout).encode(np.eye(3))
    return save(linear_model(bias, weight_scale=1.0, metadata=meta, seed=3), tmp_path_factory.mktemp("m") / "code.onnx")
