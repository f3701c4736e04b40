"""``popcode-train evaluate`` end to end on a tiny rendered split, the ground truth as a method, bad input."""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.bop19_csv import read_bop19_results
from popcode_runtime.geometry.translation import object_points_mm, translation_from_box
from popcode_runtime.inference.estimator import PoseEstimator
from popcode_trainer.cli import main
from popcode_trainer.data.hull import HULL_POINTS
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER, render_builtin_split
from popcode_trainer.eval.pipeline.evaluate import evaluate_rotations
from popcode_trainer.eval.pipeline.models import methods_from_paths
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.pipeline.split_metrics import SplitMetrics
from popcode_trainer.eval.reporting.report import write_report
from popcode_trainer.export.onnx_export import export_checkpoint
from popcode_trainer.metrics.recall import (
    GROUPS,
    Thresholds,
)
from popcode_trainer.train.config import Config
from popcode_trainer.train.loop import train
from popcode_trainer.train.run_files import LAST_CHECKPOINT
from popcode_trainer.train.training_data import build_training_data, validation_crops

OBJECTS = [3, 6]  # a 2-fold symmetric part and one without symmetry: both ambiguity groups


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return render_builtin_split(tmp_path_factory.mktemp("split"), 3, obj_ids=OBJECTS, random_position=True)


@pytest.fixture(scope="module")
def models(split: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A tiny population-code network trained one epoch on the split: its checkpoint and ONNX export."""
    run_dir = tmp_path_factory.mktemp("run")
    config = Config.from_dict({
        "data": {"splits": [str(split)], "models_dir": str(split / BUILTIN_MODELS_FOLDER), "num_workers": 0,
                 "val_fraction": 0.2},
        "code": {"n_axes": 42, "n_angles": 12, "sigma_deg": 30.0},
        "network": {"conv_channels": [4, 4, 4], "squeeze_channels": 2, "hidden": [16, 16, 16]},
        "train": {"epochs": 1, "batch_size": 2, "out_dir": str(run_dir), "device": "cpu"},
    })
    data = build_training_data(config)
    train(config, data.representation, data.train_set, data.val_set, val_instances=data.val_instances)
    crops, obj_ids = validation_crops(config)
    onnx_path = export_checkpoint(run_dir / LAST_CHECKPOINT, run_dir / "model.onnx", crops, obj_ids=obj_ids)[0].path
    return run_dir / LAST_CHECKPOINT, onnx_path


def evaluate(split: Path, out: Path, *args: str) -> int:
    return main(["evaluate", *args, "--split", str(split), "--models-dir", str(split / BUILTIN_MODELS_FOLDER),
                 "--out", str(out)])


def test_the_ground_truth_scores_full_marks(split: Path) -> None:
    eval_split = read_eval_split([split], split / BUILTIN_MODELS_FOLDER)
    R_gt = np.stack([inst.R_m2c for inst in eval_split.instances])
    metrics = SplitMetrics(eval_split)
    try:
        result = evaluate_rotations("truth", R_gt, metrics)
        errors = metrics.errors(R_gt)
    finally:
        metrics.close()
    # Not only above every threshold: the true pose has no VSD error at all, at any tau.
    assert errors.vsd is not None and not errors.vsd.any() and not errors.vss.any()
    assert sorted(result.per_object) == OBJECTS
    assert list(result.groups) == list(GROUPS)
    for scores in result.groups.values():
        assert scores == {"VSD": 1.0, "MSSD": 1.0, "MSPD": 1.0, "e_VSD<0.3": 1.0, "VSS": 1.0, "ADI": 1.0}
    assert result.tightest == {group: {"VSD": 1.0, "MSSD": 1.0, "MSPD": 1.0} for group in GROUPS}


def test_report_has_a_table_of_the_tightest_threshold_recalls(split: Path, tmp_path: Path) -> None:
    eval_split = read_eval_split([split], split / BUILTIN_MODELS_FOLDER)
    R_gt = np.stack([inst.R_m2c for inst in eval_split.instances])
    quarter_turn_x = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    metrics = SplitMetrics(eval_split)
    try:
        truth = evaluate_rotations("truth", R_gt, metrics)
        # A quarter turn in the model frame is no symmetry of either object and moves vertices far beyond 5 %.
        turned = evaluate_rotations("turned", R_gt @ quarter_turn_x, metrics)
    finally:
        metrics.close()
    write_report([truth, turned], tmp_path)
    markdown = (tmp_path / "report.md").read_text()
    title = "## Tightest thresholds (recall): MSSD < 5 % of diameter, MSPD < 5 px, VSD < 0.05 at tau = 5 % of diameter"
    assert title in markdown
    section = markdown.split(title)[1].split("## Scores per object")[0]
    assert section.count("| Method | VSD | MSSD | MSPD |") == len(GROUPS)
    assert section.count("| truth | **100.00%** | **100.00%** | **100.00%** |") == len(GROUPS)
    turned_rows = [line.split(" | ") for line in section.splitlines() if line.startswith("| turned |")]
    assert len(turned_rows) == len(GROUPS) and all(row[2] == "0.00%" for row in turned_rows)  # the MSSD column
    report = json.loads((tmp_path / "report.json").read_text())
    assert report["tightest_thresholds"] == {"mssd_fractions": 0.05, "mspd_px_at_640": 5.0, "vsd_taus": 0.05,
                                             "vsd_thetas": 0.05}
    assert report["methods"]["truth"]["tightest"] == {g: {"VSD": 1.0, "MSSD": 1.0, "MSPD": 1.0} for g in GROUPS}
    assert all(scores["MSSD"] == 0.0 for scores in report["methods"]["turned"]["tightest"].values())
    with pytest.raises(PopcodeError, match="different thresholds"):
        write_report([truth, replace(turned, thresholds=Thresholds(mssd_fractions=(0.1,)))], tmp_path / "mixed")


def test_checkpoint_and_onnx_side_by_side(split: Path, models: tuple[Path, Path], tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    ckpt, onnx_path = models
    assert evaluate(split, tmp_path, str(ckpt), str(onnx_path), "--name", "torch", "--name", "runtime",
                    "--bop19-csv") == 0
    assert "**With ambiguity**" in capsys.readouterr().out
    report = json.loads((tmp_path / "report.json").read_text())
    assert list(report["methods"]) == ["torch", "runtime"]
    assert report["instances_per_object"] == {"3": 3, "6": 3}
    for method in report["methods"].values():
        assert list(method["groups"]) == list(GROUPS)
        assert sorted(method["per_object"]) == ["3", "6"]
        assert set(method["groups"]["All objects"]) == {"VSD", "MSSD", "MSPD", "e_VSD<0.3", "VSS", "ADI"}
        assert method["model_ms_per_crop"] > 0
    rows = {name: list(csv.DictReader((tmp_path / f"errors_{name}.csv").open())) for name in ("torch", "runtime")}
    assert len(rows["torch"]) == 6
    assert {"scene_id", "im_id", "obj_id", "gt_index", "mssd_mm", "mspd_px", "adi_mm", "vss"} <= set(rows["torch"][0])
    # The runtime evaluates the exported model as torch evaluates the checkpoint: the same argmax rotations.
    for a, b in zip(rows["torch"], rows["runtime"], strict=True):
        assert float(a["mssd_mm"]) == pytest.approx(float(b["mssd_mm"]), abs=1e-6)
    assert (tmp_path / "runtime_bop19.csv").read_text().startswith("scene_id,im_id,obj_id,score,R,t,time")
    assert "| MSSD / object | 3 | 6 |" in (tmp_path / "report.md").read_text()


def test_without_depth_vsd_is_skipped_or_refused(split: Path, models: tuple[Path, Path], tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    no_depth = tmp_path / "no_depth"
    shutil.copytree(split, no_depth)
    for folder in no_depth.glob("*/depth"):
        shutil.rmtree(folder)
    assert evaluate(no_depth, tmp_path / "refused", str(models[1]), "--vsd") == 2
    assert "VSD needs depth images" in capsys.readouterr().err
    with pytest.warns(UserWarning, match="VSD, e_VSD<0.3 and VSS are skipped"):
        assert evaluate(no_depth, tmp_path / "skipped", str(models[1]), "--max-instances", "1") == 0
    report = json.loads((tmp_path / "skipped" / "report.json").read_text())
    assert report["instances_per_object"] == {"3": 1, "6": 1}
    assert set(report["methods"]["model"]["groups"]["All objects"]) == {"MSSD", "MSPD", "ADI"}


def test_models_and_objects_that_do_not_match_are_refused(split: Path, models: tuple[Path, Path], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    other = render_builtin_split(tmp_path / "other", 1, obj_ids=[5])
    assert evaluate(other, tmp_path / "out", str(models[1])) == 2
    assert "no object of the split ([5]) is known to every model" in capsys.readouterr().err
    assert evaluate(split, tmp_path / "out", str(models[1]), "--obj-ids", "5") == 2
    assert "no instances of objects [5]" in capsys.readouterr().err
    both = ["--split", str(other), str(models[1])]
    assert evaluate(split, tmp_path / "out", *both, "--obj-ids", "3", "5") == 2
    assert "'model' has no model for objects [5] (its models know [3, 6])" in capsys.readouterr().err
    with pytest.warns(UserWarning, match=r"objects \[5\] of the split are not known to every model"):
        assert evaluate(split, tmp_path / "out", *both, "--no-vsd") == 0
    with pytest.raises(PopcodeError, match="method 'same': object 3 is in both"):
        methods_from_paths([models[1], models[1]], ["same", "same"])[0].known_objects()
    with pytest.raises(PopcodeError, match="2 names for 1 models"):
        methods_from_paths([models[1]], ["a", "b"])
    eval_split = read_eval_split([split], split / BUILTIN_MODELS_FOLDER)
    metrics = SplitMetrics(eval_split, vsd=False)
    with pytest.raises(PopcodeError, match="the split has 6 instances"):
        evaluate_rotations("short", np.tile(np.eye(3), (5, 1, 1)), metrics)


def _relative_error(t_mm: np.ndarray, t_gt_mm: np.ndarray) -> float:
    return float(np.linalg.norm(t_mm - t_gt_mm) / np.linalg.norm(t_gt_mm))


def test_exported_hull_points_place_the_rendered_objects_in_their_boxes(split: Path, models: tuple[Path, Path]) -> None:
    objects = PoseEstimator(models[1]).metadata.objects
    assert all(8 <= len(objects[obj]["hull_points_mm"]) <= HULL_POINTS for obj in OBJECTS)
    hull_errors, corner_errors = [], []
    for inst in read_eval_split([split], split / BUILTIN_MODELS_FOLDER).instances:  # boxes: bbox_obj
        info = objects[inst.obj_id]
        corners = {key: value for key, value in info.items() if key != "hull_points_mm"}
        hull_errors.append(_relative_error(
            translation_from_box(inst.R_m2c, inst.box, inst.K, object_points_mm(info)), inst.t_m2c_mm))
        corner_errors.append(_relative_error(
            translation_from_box(inst.R_m2c, inst.box, inst.K, object_points_mm(corners)), inst.t_m2c_mm))
        # Each silhouette edge lies within the half pixel beyond the mask's last pixel centre, where the BOP box
        # reads it (crop.box_edges) to +-0.5 px. The distance, read from the box size, is then off by at most
        # 1 px / size, the position by 0.5 px at the focal length in x and in y; the hull points add at most 1 %
        # (data/hull.py).
        tolerance = 1.0 / min(inst.box[2:]) + 1.0 / inst.K[0, 0] + 0.01
        assert hull_errors[-1] < tolerance, (inst.obj_id, inst.box)
    assert np.mean(hull_errors) < np.mean(corner_errors) / 5  # the corners lie outside the silhouette


def test_translation_from_the_box_is_reported_beside_the_rotation_protocol(split: Path, models: tuple[Path, Path],
                                                                           tmp_path: Path) -> None:
    assert evaluate(split, tmp_path, str(models[1]), "--translation", "--bop19-csv") == 0
    full = json.loads((tmp_path / "report.json").read_text())["methods"]["model"]["full_pose"]
    assert list(full["groups"]) == list(GROUPS) and sorted(full["per_object"]) == ["3", "6"]
    for summary in (full["translation"], full["translation_gt_rotation"]):
        assert summary["median_te_mm"] >= 0 and 0 <= summary["within_2_percent"] <= summary["within_5_percent"] <= 1
    markdown = (tmp_path / "report.md").read_text()
    assert "## Full 6-D pose: translation from the box" in markdown
    assert "| model, ground-truth rotation |" in markdown and "**6-D scores**" in markdown

    rows = list(csv.DictReader((tmp_path / "errors_model.csv").open()))
    estimates = read_bop19_results(tmp_path / "model_6d_bop19.csv")
    objects = PoseEstimator(models[1]).metadata.objects
    instances = read_eval_split([split], split / BUILTIN_MODELS_FOLDER).instances
    for row, estimate, inst in zip(rows, estimates, instances, strict=True):
        # With the true rotation the fit is the runtime's, on the instance's box and camera with the model's points.
        t_fit = translation_from_box(inst.R_m2c, inst.box, inst.K, object_points_mm(objects[inst.obj_id]))
        assert float(row["te_gt_rotation_mm"]) == pytest.approx(np.linalg.norm(t_fit - inst.t_m2c_mm), abs=1e-6)
        assert float(row["te_mm"]) == pytest.approx(np.linalg.norm(estimate.t_m2c_mm - inst.t_m2c_mm), abs=1e-6)
        assert float(row["te_percent"]) == pytest.approx(100 * _relative_error(estimate.t_m2c_mm, inst.t_m2c_mm))
    assert any(row["mssd_mm_6d"] != row["mssd_mm"] for row in rows)  # the 6-D errors use the fitted translation
    assert {"vss_6d", "mspd_px_6d", "te_gt_rotation_percent"} <= set(rows[0])
