"""What evaluate's files keep of the estimates: the BOP19 CSV's score and time, the errors CSV's rotation error up
to symmetry, and several decoders of one model scored side by side.

On three cluttered images of parts 3 (2-fold) and 6 (no symmetry): the shipped model of parts 3-6 (it has a
calibrated confidence), a population code built here without one (``onnx_models.linear_model``) and a
single-variable model.
"""

from __future__ import annotations

import csv
import json
import shutil
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np
import pytest
from onnx_models import linear_model, save
from scene_fixtures import SCENE_OBJECTS, scene_objects

from popcode_runtime import PoseEstimator, read_image
from popcode_runtime.bop.bop19_csv import read_bop19_results
from popcode_runtime.coding.population_code import CodeLayout
from popcode_runtime.geometry.rotations import axis_angle_to_matrix, matrix_to_sixd, random_rotations
from popcode_runtime.geometry.symmetries import symmetry_rotations
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.cli import main
from popcode_trainer.data.objects import rotation_4x4
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, RenderSettings, render_split
from popcode_trainer.eval.pipeline.evaluate import evaluate_rotations
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.pipeline.split_metrics import SplitMetrics
from popcode_trainer.eval.reporting.report import write_report
from tools.own_parts import TUNING_PARTS, write_models
from tools.paths import SHIPPED_3_6

CALIBRATED = SHIPPED_3_6  # the shipped model with a calibrated confidence


@pytest.fixture(scope="module")
def single_model(scenes: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    meta = ModelMetadata(Representation.SINGLE_VARIABLE, CodeLayout(n_axes=42, n_angles=12), scene_objects(scenes))
    return save(linear_model(matrix_to_sixd(np.eye(3)).astype(np.float32), metadata=meta),
                tmp_path_factory.mktemp("m") / "single.onnx")


def evaluate(scenes: Path, out: Path, *args: str) -> int:
    return main(["evaluate", *args, "--split", str(scenes), "--models-dir", str(scenes / BUILTIN_MODELS_FOLDER),
                 "--out", str(out), "--no-vsd"])


def _rows(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(path.open()))


def _direct_predictions(scenes: Path, model: Path) -> list:
    """The runtime's prediction of every split instance, each image's boxes in one call as evaluate makes it."""
    estimator = PoseEstimator(model)
    instances = read_eval_split([scenes], scenes / BUILTIN_MODELS_FOLDER).instances
    by_image: dict[Path, list[int]] = defaultdict(list)
    for index, inst in enumerate(instances):
        by_image[inst.image_path].append(index)
    predictions: list = [None] * len(instances)
    for path, rows in by_image.items():
        found = estimator.predict(read_image(path), [instances[i].box for i in rows], K=instances[rows[0]].K,
                                  obj_ids=[instances[i].obj_id for i in rows])
        for row, prediction in zip(rows, found, strict=True):
            predictions[row] = prediction
    return predictions


def test_bop19_csv_carries_the_calibrated_confidence_and_the_time_of_each_image(scenes: Path,
                                                                                tmp_path: Path) -> None:
    assert evaluate(scenes, tmp_path, str(CALIBRATED), "--name", "shipped", "--bop19-csv", "--translation") == 0
    estimates = read_bop19_results(tmp_path / "shipped_bop19.csv")
    direct = _direct_predictions(scenes, CALIBRATED)
    assert len(estimates) == len(direct)
    assert all(p.confidence is not None for p in direct)
    scores = [est.score for est in estimates]
    assert len(set(scores)) > 1 and all(0.0 < s < 1.0 for s in scores)  # not the old constant 1.0
    for est, prediction in zip(estimates, direct, strict=True):
        assert est.score == pytest.approx(prediction.confidence, abs=1e-6)
        np.testing.assert_allclose(est.R_m2c, prediction.R_m2c, atol=1e-6)

    times: dict[tuple[int, int], set[float]] = defaultdict(set)
    for est in estimates:
        times[(est.scene_id, est.im_id)].add(est.time_s)
    assert all(len(found) == 1 for found in times.values())  # one time per image, on each of its rows
    assert max(Counter((e.scene_id, e.im_id) for e in estimates).values()) >= 2  # images with several estimates
    image_s = [next(iter(found)) for found in times.values()]
    assert all(s > 0 for s in image_s)
    # The images' times add up to the report's time per crop: the same measured predict calls.
    method = json.loads((tmp_path / "report.json").read_text())["methods"]["shipped"]
    assert sum(image_s) == pytest.approx(method["model_ms_per_crop"] * len(estimates) / 1000.0, rel=1e-9)
    # The 6-D file has the same scores and times beside its fitted translations.
    full = read_bop19_results(tmp_path / "shipped_6d_bop19.csv")
    assert [(e.score, e.time_s) for e in full] == [(e.score, e.time_s) for e in estimates]

    # Scored again as a results file, and written again: the file's score and time are kept.
    again = tmp_path / "again"
    assert evaluate(scenes, again, str(tmp_path / "shipped_bop19.csv"), "--name", "csv", "--bop19-csv") == 0
    rewritten = read_bop19_results(again / "csv_bop19.csv")
    assert sorted((e.scene_id, e.im_id, e.obj_id, e.score, e.time_s) for e in rewritten) == sorted(
        (e.scene_id, e.im_id, e.obj_id, e.score, e.time_s) for e in estimates)


def test_without_a_calibrator_the_score_is_the_raw_activation(scenes: Path, code_model: Path,
                                                              tmp_path: Path) -> None:
    assert evaluate(scenes, tmp_path, str(code_model), "--bop19-csv") == 0
    estimates = read_bop19_results(tmp_path / "code_bop19.csv")
    direct = _direct_predictions(scenes, code_model)
    assert all(p.confidence is None for p in direct)
    for est, prediction in zip(estimates, direct, strict=True):
        assert est.score == pytest.approx(prediction.score, rel=1e-6)
        assert est.time_s > 0


def test_rotation_error_up_to_symmetry_beside_the_raw_one(scenes: Path, tmp_path: Path) -> None:
    split = read_eval_split([scenes], scenes / BUILTIN_MODELS_FOLDER)
    R_gt = np.stack([inst.R_m2c for inst in split.instances])
    obj_ids = np.array([inst.obj_id for inst in split.instances])
    assert set(obj_ids.tolist()) == set(SCENE_OBJECTS)
    half_turn = symmetry_rotations(split.models_info[3])[1]  # part 3's declared symmetry
    symmetric = np.where((obj_ids == 3)[:, None, None], R_gt @ half_turn, R_gt)
    tilt = axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.radians(7.0))
    tilted = np.where((obj_ids == 3)[:, None, None], R_gt @ half_turn @ tilt, R_gt @ tilt)
    other = random_rotations(len(R_gt), np.random.default_rng(4))
    metrics = SplitMetrics(split, vsd=False)
    try:
        results = [evaluate_rotations(name, R, metrics)
                   for name, R in (("symmetric", symmetric), ("tilted", tilted), ("random", other))]
    finally:
        metrics.close()
    write_report(results, tmp_path)
    rows = {name: _rows(tmp_path / f"errors_{name}.csv") for name in ("symmetric", "tilted", "random")}
    columns = list(rows["symmetric"][0])
    assert columns.index("re_sym_deg") == columns.index("re_deg") + 1
    assert "re_look_alike_deg" not in columns  # no built-in part has look-alike poses
    for name, found in rows.items():
        raw = np.array([float(row["re_deg"]) for row in found])
        up_to_symmetry = np.array([float(row["re_sym_deg"]) for row in found])
        assert (up_to_symmetry <= raw + 1e-9).all(), name
        part_3 = np.array([row["obj_id"] == "3" for row in found])
        if name == "symmetric":  # the ground truth composed with the declared symmetry: no error up to it
            np.testing.assert_allclose(up_to_symmetry, 0.0, atol=1e-6)
            np.testing.assert_allclose(raw[part_3], 180.0, atol=1e-6)
        if name == "tilted":
            np.testing.assert_allclose(up_to_symmetry, 7.0, atol=1e-6)
            np.testing.assert_allclose(raw[~part_3], 7.0, atol=1e-6)  # no symmetry: both the same
            assert (raw[part_3] > 170.0).all()


def test_a_look_alike_part_gets_the_error_up_to_its_look_alike_poses(tmp_path: Path) -> None:
    """The tuning set's link looks 2-fold about z but declares nothing: an estimate half a turn off is 180 deg off
    up to its (declared) symmetries, and 0 up to its look-alike poses; a part without look-alikes has no column."""
    link = next(part for part in TUNING_PARTS if part.near_symmetric)
    models = write_models([link], tmp_path / "models")
    with pytest.warns(UserWarning, match=f"object {link.obj_id} looks 2-fold symmetric about z"):
        split_dir = render_split(models, tmp_path / "split", RenderSettings(3, seed=5), progress=False)
    split = read_eval_split([split_dir], models)
    R_gt = np.stack([inst.R_m2c for inst in split.instances])
    half_turn = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.pi)
    metrics = SplitMetrics(split, vsd=False)
    try:
        write_report([evaluate_rotations("turned", R_gt @ half_turn, metrics)], tmp_path / "eval")
    finally:
        metrics.close()
    rows = _rows(tmp_path / "eval" / "errors_turned.csv")
    assert len(rows) == 3 and list(rows[0])[4:7] == ["re_deg", "re_sym_deg", "re_look_alike_deg"]
    for row in rows:
        assert float(row["re_deg"]) == pytest.approx(180.0) and float(row["re_sym_deg"]) == pytest.approx(180.0)
        assert float(row["re_look_alike_deg"]) < 1.0  # the look-alike axis is found from surface samples


def test_a_declaration_that_fails_the_symmetry_check_is_scored_as_declared(scenes: Path, tmp_path: Path) -> None:
    """Evaluation never refused a split for its symmetry declarations; finding look-alikes must not start to."""
    copy = tmp_path / "scenes"
    shutil.copytree(scenes, copy)
    info_path = copy / BUILTIN_MODELS_FOLDER / "models_info.json"
    models_info = json.loads(info_path.read_text())
    models_info["6"]["symmetries_discrete"] = [rotation_4x4((0, 0, 1), np.pi)]  # not so
    info_path.write_text(json.dumps(models_info))
    split = read_eval_split([copy], copy / BUILTIN_MODELS_FOLDER)
    with pytest.warns(UserWarning, match=r"object 6 .*does not map the mesh onto itself.*scored as declared"):
        metrics = SplitMetrics(split, vsd=False)
    try:
        assert metrics.look_alikes == {}
        result = evaluate_rotations("truth", np.stack([inst.R_m2c for inst in split.instances]), metrics)
    finally:
        metrics.close()
    assert result.groups["All objects"]["MSSD"] == pytest.approx(1.0)


def test_several_decoders_are_methods_side_by_side(scenes: Path, code_model: Path, single_model: Path,
                                                   tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    models = [str(code_model), str(single_model), "--name", "code", "--name", "single"]
    with pytest.warns(UserWarning, match=r"decoder refined applies to population-code models only; scored once: "
                                         r"'single' \(single_variable\)") as warned:
        assert evaluate(scenes, tmp_path / "both", *models, "--decoder", "argmax", "refined") == 0
    assert len([w for w in warned if "decoder" in str(w.message)]) == 1
    assert evaluate(scenes, tmp_path / "argmax", str(code_model), "--name", "code") == 0
    assert evaluate(scenes, tmp_path / "refined", str(code_model), "--name", "code", "--decoder", "refined") == 0

    both = json.loads((tmp_path / "both" / "report.json").read_text())["methods"]
    assert list(both) == ["code", "code (refined)", "single"]
    plain = {name: json.loads((tmp_path / name / "report.json").read_text())["methods"]
             for name in ("argmax", "refined")}
    assert list(plain["refined"]) == ["code"]  # a single decoder keeps the plain name
    assert both["code"]["groups"] == plain["argmax"]["code"]["groups"]
    assert both["code (refined)"]["groups"] == plain["refined"]["code"]["groups"]
    errors = {name: _rows(path) for name, path in (
        ("argmax", tmp_path / "both" / "errors_code.csv"), ("refined", tmp_path / "both" / "errors_code_refined.csv"),
        ("plain argmax", tmp_path / "argmax" / "errors_code.csv"),
        ("plain refined", tmp_path / "refined" / "errors_code.csv"))}
    assert errors["argmax"] == errors["plain argmax"] and errors["refined"] == errors["plain refined"]
    assert errors["argmax"] != errors["refined"]  # the second method was decoded otherwise
    markdown = (tmp_path / "both" / "report.md").read_text()
    assert "| code (refined) |" in markdown and "| single |" in markdown

    # A single decoder the model cannot use is still an error, as before.
    assert evaluate(scenes, tmp_path / "bad", str(single_model), "--decoder", "refined") == 2
    assert "the refined decoder needs a population-code model" in capsys.readouterr().err
