"""``detector.ema_decay``: the moving average of a detector's weights is what a run validates, checkpoints, resumes
and exports; the last step's weights stay in the checkpoint and export on request."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnxruntime
import pytest
import torch
from torch import nn

from popcode_runtime.inference.detector import Detector
from popcode_runtime.model.detector_metadata import DETECTOR_INPUT
from popcode_trainer.cli import main as trainer
from popcode_trainer.detection.averaging import WeightAverage
from popcode_trainer.detection.export import export_detector
from popcode_trainer.train.checkpoint import load

SIZES = [f"detector.{key}={value}" for key, value in (
    ("input_width", 128), ("input_height", 96), ("widths", "[8, 8, 16, 16, 16]"), ("fpn_channels", 32),
    ("head_convs", 1), ("batch_size", 2), ("val_fraction", 0.25), ("init", '"none"'), ("ema_decay", 0.9))]


def test_the_average_follows_the_steps_with_its_decay_ramped_up() -> None:
    model = nn.Sequential(nn.Linear(2, 1), nn.BatchNorm1d(1))
    average = WeightAverage(model, decay=0.9)
    first = model[0].weight.detach().clone()
    with torch.no_grad():
        model[0].weight.add_(1.0)
    average.update(model)  # decay min(0.9, 2 / 11)
    expected = first * (2 / 11) + (first + 1.0) * (9 / 11)
    assert torch.allclose(average.model[0].weight, expected)
    for _ in range(200):
        average.update(model)
    assert torch.allclose(average.model[0].weight, first + 1.0, atol=1e-6)
    assert not any(p.requires_grad for p in average.model.parameters())
    assert int(average.model[1].num_batches_tracked) == int(model[1].num_batches_tracked)


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("averaging") / "scenes"
    assert trainer(["render", "--objects", "builtin", "--out", str(out), "--scenes", "4", "--size", "128", "96",
                    "--seed", "5", "--quiet"]) == 0
    return out


def test_a_run_with_an_average_resumes_it_and_exports_it(split: Path, tmp_path: Path) -> None:
    run = tmp_path / "run"
    settings = [arg for setting in SIZES for arg in ("--set", setting)]
    assert trainer(["train-detector", "--split", str(split), "--out", str(run), "--quiet", *settings,
                    "--set", "detector.epochs=1"]) == 0
    steps = load(run / "detector.pt")["ema"]["updates"]
    assert steps == 1  # three training frames at batch 2, the last part-batch dropped
    assert trainer(["train-detector", "--split", str(split), "--out", str(run), "--quiet", *settings,
                    "--set", "detector.epochs=2"]) == 0
    state = load(run / "detector.pt")
    assert state["ema"]["updates"] == 2 * steps  # went on from the saved average
    averaged = {name: tensor for name, tensor in state["ema"]["weights"].items() if tensor.is_floating_point()}
    assert any(not torch.equal(tensor, state["model"][name]) for name, tensor in averaged.items())

    frame = np.random.default_rng(1).random((1, 1, 96, 128), np.float32)
    outputs = {}
    for averaged_weights in (True, False):
        path = export_detector(run / "detector.pt", tmp_path / f"detector-{averaged_weights}.onnx",
                               averaged=averaged_weights)
        assert Detector(path).metadata.training["weights"] == \
            ("moving average of the steps" if averaged_weights else "the last step's")
        session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        outputs[averaged_weights] = session.run(None, {DETECTOR_INPUT: frame})[1]
    assert not np.allclose(outputs[True], outputs[False])
    assert Detector(run / "detector.onnx").metadata.training["weights"] == "moving average of the steps"
