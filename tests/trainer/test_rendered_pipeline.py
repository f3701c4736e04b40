"""The whole path on real rendered data: render -> train (CLI) -> export (CLI) -> runtime predict."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from popcode_runtime import PoseEstimator, read_image
from popcode_runtime.geometry.rotations import geodesic_angle
from popcode_trainer.cli import main
from popcode_trainer.data.bop import read_bop_split
from popcode_trainer.data.render import render_builtin_split

OBJ_ID = 3  # the 2-fold block


@pytest.mark.slow
def test_train_export_predict_on_rendered_split(tmp_path: Path) -> None:
    split = render_builtin_split(tmp_path / "split", images_per_object=24, obj_ids=[OBJ_ID])
    config = tmp_path / "tiny.toml"
    config.write_text(f"""
[data]
splits = ["{split}"]
models_dir = "{split / 'models'}"
obj_ids = [{OBJ_ID}]
val_fraction = 0.25
num_workers = 0
[code]
n_axes = 162
n_angles = 12
[network]
conv_channels = [8, 16, 16]
squeeze_channels = 4
hidden = [64, 32, 32]
[train]
epochs = 4
batch_size = 6
lr = 2e-3
out_dir = "{tmp_path / 'run'}"
""")
    assert main(["train", "--config", str(config)]) == 0
    with open(tmp_path / "run" / "metrics.csv", newline="") as handle:
        losses = [float(row["train_loss"]) for row in csv.DictReader(handle)]
    assert len(losses) == 4 and losses[-1] < losses[0]

    model = tmp_path / "model.onnx"
    assert main(["export", str(tmp_path / "run" / "last.pt"), "--out", str(model)]) == 0
    estimator = PoseEstimator(model)
    assert estimator.metadata.objects.keys() == {OBJ_ID}
    assert estimator.metadata.training["epochs"] == 4

    instance = read_bop_split(split, split / "models").instances[0]
    prediction = estimator.predict(read_image(instance.image_path), [instance.box], K=instance.K,
                                   translation=True)[0]
    np.testing.assert_allclose(prediction.R_m2c @ prediction.R_m2c.T, np.eye(3), atol=1e-9)
    assert np.isfinite(geodesic_angle(prediction.R_m2c, instance.R_m2c))
    # The translation from the box lies along the true viewing ray, at a plausible distance.
    t_true = instance.t_m2c_mm
    cosine = prediction.t_m2c_mm @ t_true / (np.linalg.norm(prediction.t_m2c_mm) * np.linalg.norm(t_true))
    assert cosine > 0.99 and 0.5 < prediction.t_m2c_mm[2] / t_true[2] < 2.0
