"""`popcode-train evaluate --depth [--refine]`: 6-D poses from depth beside the box's, fallbacks counted, bad input."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from onnx_models import linear_model, save
from scene_fixtures import scene_objects

from popcode_runtime import read_image
from popcode_runtime.bop.bop19_csv import read_bop19_results
from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.depth.surface_fit import read_depth
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.cli import main
from popcode_trainer.data.hull import with_hull_points
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.eval.pipeline.split import read_eval_split


def evaluate(split: Path, out: Path, *args: str) -> int:
    return main(["evaluate", *args, "--split", str(split), "--models-dir", str(split / BUILTIN_MODELS_FOLDER),
                 "--out", str(out), "--threads", "1"])


def code_model_with(objects: dict, path: Path) -> Path:
    """A population code whose peak the crop's pixels move, knowing ``objects``."""
    layout = CodeLayout(n_axes=162, n_angles=12, sigma_deg=30.0)
    meta = ModelMetadata(Representation.POPULATION_CODE, layout, objects)
    return save(linear_model(PopulationCode(layout).encode(np.eye(3)), weight_scale=1.0, metadata=meta, seed=3), path)


@pytest.fixture(scope="module")
def depth_model(scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The model with the surface points an export writes."""
    objects = with_hull_points(scene_objects(scenes), scenes / BUILTIN_MODELS_FOLDER)
    return code_model_with(objects, tmp_path_factory.mktemp("m") / "model.onnx")


@pytest.fixture(scope="module")
def blind_split(scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int]:
    """The scenes with the first image's depth all zeros (a camera that saw nothing there), and how many of the
    evaluated instances are in that image."""
    split = tmp_path_factory.mktemp("blind") / "split"
    shutil.copytree(scenes, split)
    first = read_eval_split([split], split / BUILTIN_MODELS_FOLDER).instances[0]
    depth = cv2.imread(str(first.depth_path), cv2.IMREAD_ANYDEPTH)
    cv2.imwrite(str(first.depth_path), np.zeros_like(depth))
    instances = read_eval_split([split], split / BUILTIN_MODELS_FOLDER).instances
    return split, sum(inst.image_path == first.image_path for inst in instances)


def test_depth_rows_beside_the_box_with_fallbacks_counted(blind_split: tuple[Path, int], depth_model: Path,
                                                          tmp_path: Path) -> None:
    split, blind = blind_split
    assert evaluate(split, tmp_path, str(depth_model), "--depth", "--refine", "--bop19-csv") == 0
    method = json.loads((tmp_path / "report.json").read_text())["methods"]["model"]
    instances = read_eval_split([split], split / BUILTIN_MODELS_FOLDER).instances
    assert "full_pose" in method  # --depth implies the box's 6-D rows
    for mode in ("depth", "refined"):
        posed = method["depth"][mode]
        assert sum(posed["sources"].values()) == len(instances)
        assert posed["sources"]["box"] >= blind and posed["notes"]["no valid depth in the box"] == blind
        assert 0.0 <= posed["translation"]["within_2_mm"] <= posed["translation"]["within_5_mm"] <= 1.0
        assert 0.0 <= posed["groups"]["All objects"]["MSSD"] <= 1.0 and "VSD" in posed["groups"]["All objects"]
        assert posed["depth_ms_per_instance"] > 0
    assert set(method["depth"]["refined"]["sources"]) <= {"refined", "depth", "box"}

    markdown = (tmp_path / "report.md").read_text()
    assert "## Full 6-D pose: translation from the box and from depth" in markdown
    assert "| model, depth |" in markdown and "| model, depth + ICP |" in markdown  # translation and 6-D rows
    assert "| Method, depth | translation from |" in markdown and "no valid depth in the box" in markdown

    rows = list(csv.DictReader((tmp_path / "errors_model.csv").open()))
    assert {"te_depth_mm", "t_source_depth", "depth_note_refined", "mssd_mm_6d_refined", "vss_6d_depth"} <= set(rows[0])
    assert [row["depth_note_depth"] for row in rows[:blind]] == ["no valid depth in the box"] * blind

    # One definition: the translations are the runtime's predict with the image's depth.
    estimates = read_bop19_results(tmp_path / "model_6d_depth_bop19.csv")
    image = [i for i, inst in enumerate(instances) if inst.image_path == instances[-1].image_path]
    predictions = PoseEstimator(depth_model).predict(
        read_image(instances[-1].image_path), [instances[i].box for i in image],
        K=instances[-1].K, obj_ids=[instances[i].obj_id for i in image], depth=read_depth(instances[-1].depth_path),
        depth_scale=instances[-1].depth_scale)
    for i, prediction in zip(image, predictions, strict=True):
        np.testing.assert_allclose(estimates[i].t_m2c_mm, prediction.t_m2c_mm, atol=1e-6)
        assert rows[i]["t_source_depth"] == prediction.t_source


def test_bad_depth_input_is_one_line(scenes: Path, depth_model: Path, tmp_path: Path,
                                     capsys: pytest.CaptureFixture) -> None:
    no_depth = tmp_path / "no-depth"
    shutil.copytree(scenes, no_depth)
    for folder in no_depth.glob("*/depth"):
        shutil.rmtree(folder)
    plain = code_model_with(scene_objects(scenes), tmp_path / "plain.onnx")  # exported before surface points
    cases = [((no_depth, str(depth_model), "--depth"), "have no depth image"),
             ((scenes, str(depth_model), "--refine"), "--refine refines each pose against its image's depth"),
             ((scenes, str(plain), "--depth"), f"{plain}: this model carries no surface points")]
    for (split, *args), message in cases:
        assert evaluate(split, tmp_path / "out", *args) == 2
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()  # refused before any work
