"""The README's "Training on your own CAD models", step by step, on a part made here.

The commands are the README's (render, preview, train with quick.toml, export,
predict); only the sizes shrink (--set) so the test runs in seconds.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from popcode_runtime.cli import main as runtime_main
from popcode_trainer.cli import main
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.objects import model_info
from popcode_trainer.demo.run import DEMO_SIZES
from popcode_trainer.train.config import load_config

QUICK = Path(__file__).resolve().parents[2] / "trainer" / "configs" / "quick.toml"


def _t_bracket() -> trimesh.Trimesh:
    """A part without symmetry: a T of two bars and a peg on one arm (mm)."""
    bar = trimesh.creation.box((80.0, 16.0, 12.0))
    stem = trimesh.creation.box((16.0, 50.0, 12.0))
    stem.apply_translation((0.0, -33.0, 0.0))
    peg = trimesh.creation.cylinder(radius=5.0, height=18.0)
    peg.apply_translation((28.0, 0.0, 15.0))
    mesh = trimesh.util.concatenate([bar, stem, peg])
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def _write_models(folder: Path) -> Path:
    folder.mkdir(parents=True)
    mesh = _t_bracket()
    mesh.export(folder / "obj_000001.ply")
    (folder / "models_info.json").write_text(json.dumps({"1": model_info(mesh, {})}))
    return folder


def test_quick_config_is_the_demo_recipe() -> None:
    quick = load_config(QUICK)
    demo = DEMO_SIZES["quick"].pipeline.config
    paths = {"splits", "models_dir", "obj_ids"}
    assert {k: v for k, v in quick.to_dict()["data"].items() if k not in paths} == \
        {k: v for k, v in demo.to_dict()["data"].items() if k not in paths}
    assert quick.to_dict()["code"] == demo.to_dict()["code"]
    assert quick.to_dict()["network"] == demo.to_dict()["network"]
    train = {k: v for k, v in quick.to_dict()["train"].items() if k != "out_dir"}
    assert train == {k: v for k, v in demo.to_dict()["train"].items() if k != "out_dir"}


@pytest.mark.slow
def test_own_part_render_preview_train_export_predict(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    models = _write_models(tmp_path / "models")
    split = tmp_path / "data" / "mine"
    assert main(["render", "--objects", str(models), "--out", str(split), "--images", "12", "--random-position",
                 "--quiet"]) == 0
    assert main(["preview", "--split", str(split), "--models", str(models), "--out", str(tmp_path / "crops.png"),
                 "--count", "4"]) == 0
    assert (tmp_path / "crops.png").stat().st_size > 0

    run = tmp_path / "runs" / "mine"
    assert main(["train", "--config", str(QUICK), "--set", f'data.splits=["{split}"]',
                 "--set", f'data.models_dir="{models}"', "--set", f'train.out_dir="{run}"',
                 "--set", "train.epochs=2", "--set", "train.batch_size=4", "--set", "data.val_fraction=0.25"]) == 0
    model = tmp_path / "mine.onnx"
    assert main(["export", str(run / "best.pt"), "--out", str(model)]) == 0

    instance = read_bop_split(split, models).instances[0]
    box = ",".join(f"{v:.1f}" for v in instance.box)
    capsys.readouterr()
    assert runtime_main(["predict", str(model), str(instance.image_path), f"--box={box}", "--json"]) == 0
    predictions = json.loads(capsys.readouterr().out)["predictions"]
    assert len(predictions) == 1 and predictions[0]["obj_id"] == 1
    R = np.asarray(predictions[0]["R_m2c"])
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)
