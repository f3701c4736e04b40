"""Scoring with a detector's boxes (``evaluate --box-noise``), by the best of the top-k hypotheses (``--top-k``),
and the chain ``popcode-train detections`` -> ``popcode run --detections`` -> ``popcode-train evaluate``.

The models are small ONNX files built here (``onnx_models.linear_model``), no training: a population code
whose argmax moves with the crop (so boxes matter), one with two known peaks, and a single-variable model.
"""

from __future__ import annotations

import csv
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from onnx_models import linear_model, save
from scene_fixtures import SCENE_SIZE, scene_objects

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.bop.bop19_csv import read_bop19_results
from popcode_runtime.bop.detections import read_detections
from popcode_runtime.coding.population_code import CodeLayout, PopulationCode
from popcode_runtime.commands.cli import main as popcode_main
from popcode_runtime.geometry.rotations import matrix_to_sixd
from popcode_runtime.model.metadata import ModelMetadata, Representation
from popcode_trainer.cli import main
from popcode_trainer.data.box_noise import IOU_BINS, box_iou, box_noise_preset, iou_bin_label
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.eval.pipeline.detector_boxes import with_detector_boxes
from popcode_trainer.eval.pipeline.evaluate import evaluate_models
from popcode_trainer.eval.pipeline.models import methods_from_paths
from popcode_trainer.eval.pipeline.split import read_eval_split, restrict_to_objects
from popcode_trainer.metrics.recall import GROUPS

QUARTER_TURN_X = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


def evaluate(scenes: Path, out: Path, *args: str) -> int:
    return main(["evaluate", *args, "--split", str(scenes), "--models-dir", str(scenes / BUILTIN_MODELS_FOLDER),
                 "--out", str(out), "--no-vsd"])


def _rows(path: Path) -> list[dict[str, str]]:
    return list(csv.DictReader(path.open()))


def test_box_noise_none_is_the_ground_truth_protocol(scenes: Path, code_model: Path, tmp_path: Path) -> None:
    assert evaluate(scenes, tmp_path / "plain", str(code_model), "--translation") == 0
    assert evaluate(scenes, tmp_path / "none", str(code_model), "--translation", "--box-noise", "none") == 0
    plain, none = _rows(tmp_path / "plain" / "errors_code.csv"), _rows(tmp_path / "none" / "errors_code.csv")
    assert "box_iou" not in plain[0] and [float(row.pop("box_iou")) for row in none] == [1.0] * len(none)
    assert none == plain  # every error, 6-D ones too: the same boxes reached the model and the translation fit
    reports = [json.loads((tmp_path / name / "report.json").read_text()) for name in ("plain", "none")]
    assert "box_noise" not in reports[0] and reports[1]["box_noise"] == {"preset": "none", "seed": 0, "mean_iou": 1.0}
    methods = [report["methods"]["code"] for report in reports]
    assert "by_box_iou" not in methods[0] and methods[1].pop("by_box_iou")[iou_bin_label(*IOU_BINS[-1])][
        "instances"] == len(plain)
    for method in methods:
        for timing in ("model_ms_per_crop", "metric_s"):
            method.pop(timing)
    assert methods[0] == methods[1]
    assert "box IoU" not in (tmp_path / "plain" / "report.md").read_text()


def test_loose_boxes_are_scored_per_iou_bin(scenes: Path, code_model: Path, tmp_path: Path) -> None:
    assert evaluate(scenes, tmp_path / "loose", str(code_model), "--box-noise", "loose", "--box-noise-seed", "3") == 0
    assert evaluate(scenes, tmp_path / "plain", str(code_model)) == 0
    rows, plain = _rows(tmp_path / "loose" / "errors_code.csv"), _rows(tmp_path / "plain" / "errors_code.csv")
    iou = np.array([float(row["box_iou"]) for row in rows])
    assert 0.4 < iou.mean() < 0.8 and (iou < 1.0).all()
    assert any(a["mssd_mm"] != b["mssd_mm"] for a, b in zip(rows, plain, strict=True))  # the model saw other crops
    report = json.loads((tmp_path / "loose" / "report.json").read_text())
    assert report["box_noise"]["preset"] == "loose" and report["box_noise"]["seed"] == 3
    bins = report["methods"]["code"]["by_box_iou"]
    assert list(bins) == [iou_bin_label(low, high) for low, high in IOU_BINS]
    assert sum(scores["instances"] for scores in bins.values()) == len(rows) == sum(report["instances_per_object"]
                                                                                   .values())
    for (low, high), scores in zip(IOU_BINS, bins.values(), strict=True):
        assert scores["instances"] == ((iou >= low) & (iou < high)).sum()
    markdown = (tmp_path / "loose" / "report.md").read_text()
    section = markdown.split("## MSSD by box IoU")[1].split("## ")[0]
    counts = next(line for line in section.splitlines() if line.startswith("| Instances |"))
    assert sum(int(cell) for cell in counts.strip("| \n").split(" | ")[1:]) == len(rows)
    assert "preset 'loose', seed 3" in section and "| code |" in section


def test_detector_boxes_stay_in_the_image_and_follow_their_instances(scenes: Path) -> None:
    split = read_eval_split([scenes], scenes / BUILTIN_MODELS_FOLDER)
    width, height = SCENE_SIZE
    assert any(inst.box[1] + inst.box[3] > height or inst.box[0] + inst.box[2] > width or min(inst.box[:2]) < 0
               for inst in split.instances), "no box cut by the border"
    noisy = with_detector_boxes(split, box_noise_preset("loose"), seed=1)
    for inst, moved, iou in zip(split.instances, noisy.instances, noisy.detector_boxes.iou, strict=True):
        x, y, w, h = moved.box
        assert x >= 0 and y >= 0 and x + w <= SCENE_SIZE[0] and y + h <= SCENE_SIZE[1]
        assert iou == box_iou(inst.box, moved.box) and moved.scene_id == inst.scene_id and moved.R_m2c is inst.R_m2c
    # Each box is drawn for its instance alone: fewer instances, the same boxes and IoUs.
    only_6 = restrict_to_objects(noisy, [6])
    alone = with_detector_boxes(restrict_to_objects(split, [6]), box_noise_preset("loose"), seed=1)
    assert [i.box for i in only_6.instances] == [i.box for i in alone.instances]
    assert only_6.detector_boxes.iou.tolist() == alone.detector_boxes.iou.tolist()
    with pytest.raises(PopcodeError, match="already a detector's"):
        with_detector_boxes(noisy, box_noise_preset("tight"))


def test_detections_file_runs_through_popcode_run_and_evaluate(scenes: Path, code_model: Path, tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    detections, results = tmp_path / "detections.json", tmp_path / "results.csv"
    assert main(["detections", "--split", str(scenes), "--box-noise", "detector", "--seed", "5",
                 "--out", str(detections)]) == 0
    assert "box-noise preset 'detector' seed 5" in capsys.readouterr().out
    split = read_eval_split([scenes], scenes / BUILTIN_MODELS_FOLDER)
    noisy = with_detector_boxes(split, box_noise_preset("detector"), seed=5)
    written = read_detections(detections)
    assert [(d.scene_id, d.im_id, d.obj_id, d.box) for d in written] == [
        (i.scene_id, i.im_id, i.obj_id, i.box) for i in noisy.instances]  # evaluate --box-noise crops these boxes
    assert json.loads(detections.read_text())[0].keys() == {"scene_id", "image_id", "category_id", "bbox", "score",
                                                            "time"}

    assert popcode_main(["run", str(code_model), "--split", str(scenes), "--detections", str(detections),
                         "--out", str(results), "--quiet"]) == 0
    out = tmp_path / "eval"
    assert evaluate(scenes, out, str(code_model), str(results), "--name", "model", "--name", "run",
                    "--box-noise", "detector", "--box-noise-seed", "5", "--bop19-csv") == 0
    # popcode run on the file estimated what evaluate estimated on its own detector boxes: per image and object,
    # the same rotations (a results file is matched to instances by rotation, so compare them as sets).
    rotations: list[dict[tuple[int, int, int], list[np.ndarray]]] = [defaultdict(list), defaultdict(list)]
    for found, path in zip(rotations, (results, out / "model_bop19.csv"), strict=True):
        for est in read_bop19_results(path):
            found[(est.scene_id, est.im_id, est.obj_id)].append(est.R_m2c.ravel())
    assert rotations[0].keys() == rotations[1].keys() and sum(map(len, rotations[0].values())) == len(split.instances)
    for key, from_run in rotations[0].items():
        np.testing.assert_allclose(sorted(map(tuple, from_run)), sorted(map(tuple, rotations[1][key])), atol=1e-5)
    report = json.loads((out / "report.json").read_text())
    assert report["methods"]["run"]["groups"]["All objects"]["MSSD"] >= 0 and "by_box_iou" in report["methods"]["run"]


def _two_peak_model(scenes: Path, path: Path) -> tuple[Path, int]:
    """A constant code with its strongest peak a quarter turn from one instance's true rotation and a weaker one
    at it: the argmax is wrong there, the second hypothesis right. Returns the model and that instance."""
    split = read_eval_split([scenes], scenes / BUILTIN_MODELS_FOLDER)
    index = next(i for i, inst in enumerate(split.instances) if inst.obj_id == 6)  # no symmetry
    R_gt = split.instances[index].R_m2c
    layout = CodeLayout(n_axes=642, n_angles=36, sigma_deg=20.0)
    code = PopulationCode(layout)
    bias = code.encode(R_gt @ QUARTER_TURN_X) + 0.6 * code.encode(R_gt)
    meta = ModelMetadata(Representation.POPULATION_CODE, layout, scene_objects(scenes))
    return save(linear_model(bias, metadata=meta), path), index


def _single_variable_model(scenes: Path, path: Path) -> Path:
    meta = ModelMetadata(Representation.SINGLE_VARIABLE, CodeLayout(n_axes=42, n_angles=12), scene_objects(scenes))
    return save(linear_model(matrix_to_sixd(np.eye(3)).astype(np.float32), metadata=meta), path)


def test_best_of_the_top_k_hypotheses(scenes: Path, tmp_path: Path) -> None:
    two_peaks, index = _two_peak_model(scenes, tmp_path / "two_peaks.onnx")
    single = _single_variable_model(scenes, tmp_path / "single.onnx")
    models = [str(two_peaks), str(single), "--name", "code", "--name", "single"]
    assert evaluate(scenes, tmp_path / "top3", *models, "--top-k", "3") == 0
    assert evaluate(scenes, tmp_path / "top1", *models) == 0

    methods = json.loads((tmp_path / "top3" / "report.json").read_text())["methods"]
    best = methods["code"]["best_of_top_k"]
    assert list(best) == ["1", "2", "3"] and methods["single"]["best_of_top_k"] is None
    for group in GROUPS:
        assert best["1"][group] == methods["code"]["groups"][group]["MSSD"]  # the best of one is the estimate
        assert best["1"][group] <= best["2"][group] <= best["3"][group]
    assert best["2"]["Without ambiguity"] > best["1"]["Without ambiguity"]  # the instance whose second peak is right
    rows = _rows(tmp_path / "top3" / "errors_code.csv")
    mssd = np.array([float(row["mssd_mm"]) for row in rows])
    top3 = np.array([float(row["mssd_mm_best_of_top3"]) for row in rows])
    assert (top3 <= mssd).all() and top3[index] < 0.3 * mssd[index]
    assert "mssd_mm_best_of_top3" not in _rows(tmp_path / "top3" / "errors_single.csv")[0]

    section = (tmp_path / "top3" / "report.md").read_text().split("## MSSD of the best of the top-3 hypotheses")[1]
    assert "| Method | MSSD (estimate) | MSSD (best of top-2) | MSSD (best of top-3) |" in section
    assert sum(line.startswith("| single |") and line.endswith("| – | – |") for line in section.splitlines()) == 3
    plain = json.loads((tmp_path / "top1" / "report.json").read_text())["methods"]
    assert "best_of_top_k" not in plain["code"] and "best of the top" not in (tmp_path / "top1" / "report.md"
                                                                             ).read_text()
    assert plain["code"]["groups"] == methods["code"]["groups"]  # hypotheses leave the estimate alone


@pytest.mark.parametrize(("args", "message"), [
    (["evaluate", "--box-noise", "wild"],
     "popcode-train: error: unknown box-noise preset 'wild'; choose one of ['none', 'tight', 'detector', 'loose']"),
    (["evaluate", "--top-k", "0"], "popcode-train: error: --top-k must lie in [1, 100], got 0"),
    (["evaluate", "--top-k", "101"], "popcode-train: error: --top-k must lie in [1, 100], got 101"),
    (["evaluate", "--box-noise", "loose", "--box-noise-seed", "-1"],
     "popcode-train: error: --box-noise-seed must be 0 or more, got -1"),
    (["detections", "--box-noise", "wild"],
     "popcode-train: error: unknown box-noise preset 'wild'; choose one of ['none', 'tight', 'detector', 'loose']"),
    (["detections", "--box-noise", "loose", "--min-visib-fract", "2"],
     "popcode-train: error: --min-visib-fract must lie in [0, 1], got 2.0"),
])
def test_bad_options_end_with_one_line(scenes: Path, code_model: Path, tmp_path: Path, args: list[str], message: str,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    command, *options = args
    if command == "evaluate":
        argv = [command, str(code_model), "--split", str(scenes), "--models-dir", str(scenes / BUILTIN_MODELS_FOLDER),
                "--out", str(tmp_path / "out"), *options]
    else:
        argv = [command, "--split", str(scenes), "--out", str(tmp_path / "d.json"), *options]
    assert main(argv) == 2
    assert capsys.readouterr().err.splitlines() == [message]
    assert not (tmp_path / "out").exists() and not (tmp_path / "d.json").exists()


def test_top_k_is_checked_in_python_too(scenes: Path, code_model: Path) -> None:
    split = read_eval_split([scenes], scenes / BUILTIN_MODELS_FOLDER)
    with pytest.raises(PopcodeError, match="top_k must lie in"):
        evaluate_models(methods_from_paths([code_model]), split, vsd=False, top_k=0)
