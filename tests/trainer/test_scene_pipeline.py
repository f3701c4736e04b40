"""A cluttered scene split end to end: occluded and border-cut crops train, evaluation scores per visibility bin."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from popcode_trainer.cli import main
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.render import BUILTIN_MODELS_FOLDER
from popcode_trainer.data.scene_render import render_cluttered_test_split
from popcode_trainer.eval.pipeline.evaluate import evaluate_rotations
from popcode_trainer.eval.pipeline.split import read_eval_split
from popcode_trainer.eval.pipeline.split_metrics import SplitMetrics
from popcode_trainer.eval.reporting.report import write_report
from popcode_trainer.metrics.recall import VISIBILITY_BINS
from popcode_trainer.train.config import Config
from popcode_trainer.train.loop import train
from popcode_trainer.train.run_files import LAST_CHECKPOINT
from popcode_trainer.train.training_data import build_training_data

SIZE = (160, 120)
FULL_CODE_PARTS = [3, 4, 5, 6]  # one model cannot pool them with the continuously symmetric 1 and 2


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return render_cluttered_test_split(tmp_path_factory.mktemp("scenes"), scenes=8, size=SIZE, sensor="webcam",
                                       parts=(4, 7), fill_range=(0.9, 1.4))


def _cut_by_border(box: tuple[float, float, float, float]) -> bool:
    x, y, w, h = box
    return x < 0 or y < 0 or x + w >= SIZE[0] or y + h >= SIZE[1]


@pytest.mark.slow
def test_occluded_and_border_cut_crops_train_and_evaluate(scenes: Path, tmp_path: Path) -> None:
    models_dir = scenes / BUILTIN_MODELS_FOLDER
    config = Config.from_dict({
        "data": {"splits": [str(scenes)], "models_dir": str(models_dir), "num_workers": 0, "val_fraction": 0.25,
                 "min_visib_fract": 0.3, "box": "bbox_obj", "obj_ids": FULL_CODE_PARTS},
        "code": {"n_axes": 42, "n_angles": 12, "sigma_deg": 30.0},
        "network": {"conv_channels": [4, 4, 4], "squeeze_channels": 2, "hidden": [16, 16, 16]},
        "train": {"epochs": 1, "batch_size": 8, "out_dir": str(tmp_path / "run"), "device": "cpu"},
    })
    data = build_training_data(config, progress=False)
    instances = data.train_set.instances
    assert any(inst.visib_fract < 0.9 for inst in instances), "no occluded training crop"
    cut = [i for i, inst in enumerate(instances) if _cut_by_border(inst.box)]
    assert cut, "no training crop cut by the image border"
    for index in cut:
        crop = data.train_set.crop(index)
        assert crop.shape == (128, 128) and np.isfinite(crop).all() and crop.std() > 0
    train(config, data.representation, data.train_set, data.val_set, val_instances=data.val_instances)

    out = tmp_path / "eval"
    assert main(["evaluate", str(tmp_path / "run" / LAST_CHECKPOINT), "--split", str(scenes), "--models-dir",
                 str(models_dir), "--out", str(out), "--no-vsd", "--obj-ids",
                 *map(str, FULL_CODE_PARTS)]) == 0
    report = json.loads((out / "report.json").read_text())
    bins = next(iter(report["methods"].values()))["by_visibility"]
    assert list(bins) == [label for label, _, _ in VISIBILITY_BINS]
    evaluated = read_bop_split(scenes, models_dir, obj_ids=FULL_CODE_PARTS, min_visib_fract=0.1).instances
    assert sum(scores["instances"] for scores in bins.values()) == len(evaluated)
    assert "## Scores by visibility" in (out / "report.md").read_text()


def test_visibility_bins_hold_each_instance_once(scenes: Path, tmp_path: Path) -> None:
    split = read_eval_split([scenes], scenes / BUILTIN_MODELS_FOLDER)
    visib = np.array([inst.visib_fract for inst in split.instances])
    assert visib.min() >= 0.1 and (visib < 0.6).any() and (visib >= 0.9).any()
    R_gt = np.stack([inst.R_m2c for inst in split.instances])
    metrics = SplitMetrics(split, vsd=False)
    try:
        truth = evaluate_rotations("truth", R_gt, metrics)
        quarter_turn_x = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
        turned = evaluate_rotations("turned", R_gt @ quarter_turn_x, metrics)
    finally:
        metrics.close()
    for label, low, high in VISIBILITY_BINS:
        count = int(((visib >= low) & (visib < high)).sum())
        assert truth.by_visibility[label]["instances"] == count
        if count:
            assert truth.by_visibility[label]["MSSD"] == 1.0
            assert turned.by_visibility[label]["MSSD"] < 1.0
        else:
            assert np.isnan(truth.by_visibility[label]["MSSD"])
    write_report([truth, turned], tmp_path)
    section = (tmp_path / "report.md").read_text().split("## Scores by visibility")[1].split("## Scores per object")[0]
    assert section.count("| Method | MSSD | MSPD | ADI |") == len(VISIBILITY_BINS)
