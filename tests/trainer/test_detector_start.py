"""Detector starts (detection.start): written and read back, copied into a detector of other objects but the
classification logits, taken by training through detector.init and recorded in the export, and every file that is
not a detector start of this network refused in one line."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from popcode_runtime.base.errors import PopcodeError
from popcode_runtime.inference.detector import Detector
from popcode_trainer.cli import main as trainer
from popcode_trainer.demo.sizes import DEMO_DETECTOR, DEMO_SIZES
from popcode_trainer.detection.config import DetectorConfig
from popcode_trainer.detection.network import CLASS_LOGITS, build_detector
from popcode_trainer.detection.start import (
    apply_start,
    resolve_detector_start,
    shipped_detector_start,
    write_detector_start,
)
from popcode_trainer.train import pretrained
from popcode_trainer.train.network import NetworkConfig, build_network

TINY = DetectorConfig(input_width=128, input_height=96, widths=(8, 8, 16, 16, 16), fpn_channels=32, head_convs=1,
                      batch_size=4, val_fraction=0.25, epochs=1)
CARD = {"parts": 7, "epochs": 3, "commit": "abc1234"}


def _start(folder: Path, config: DetectorConfig = TINY) -> tuple[Path, torch.nn.Module]:
    model = build_detector(replace(config, seed=5), 7)
    return write_detector_start(model, config, folder / "detector-start.pt", CARD), model


def test_a_start_fills_every_layer_of_a_detector_of_other_objects_but_its_logits(tmp_path: Path) -> None:
    path, source = _start(tmp_path)
    start, line = resolve_detector_start(replace(TINY, init=str(path)))
    assert start is not None and start.card == CARD and "7 generated parts" in line
    target = build_detector(TINY, 3)  # another number of objects: its logits are its own
    logits_before = {k: v.clone() for k, v in target.state_dict().items() if k.startswith(CLASS_LOGITS)}
    copied = apply_start(target, start)
    assert copied == len(start.state) and not any(name.startswith(CLASS_LOGITS) for name in start.state)
    for name in start.state:
        torch.testing.assert_close(target.state_dict()[name], source.state_dict()[name], msg=name)
    for name, tensor in logits_before.items():
        torch.testing.assert_close(target.state_dict()[name], tensor, msg=name)


def test_a_start_of_another_detector_shape_is_refused_naming_the_difference(tmp_path: Path) -> None:
    path, _ = _start(tmp_path)
    wider = replace(TINY, widths=(8, 8, 16, 16, 32), init=str(path))
    with pytest.raises(PopcodeError, match=r"another network \(detector.widths \[8, 8, 16, 16, 16\] there, "
                                           r"\[8, 8, 16, 16, 32\] here\)"):
        resolve_detector_start(wider)


def test_files_that_are_not_detector_starts_are_refused_in_one_line(tmp_path: Path) -> None:
    network = NetworkConfig(output_dim=42 * 12, input_size=128, conv_channels=(8, 8, 8), squeeze_channels=4,
                            hidden=(32, 32, 32))
    pose_start = pretrained.write_start(build_network(network), network, tmp_path / "pose.pt", CARD)
    with pytest.raises(PopcodeError, match="is not a detector start .*'popcode-detector-start'"):
        resolve_detector_start(replace(TINY, init=str(pose_start)))
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(PopcodeError):
        resolve_detector_start(replace(TINY, init=str(tmp_path / "junk.pt")))
    with pytest.raises(PopcodeError, match="detector start not found: .*detector.init is 'auto', 'none'"):
        resolve_detector_start(replace(TINY, init=str(tmp_path / "missing.pt")))
    with pytest.raises(PopcodeError, match="detector init must be"):
        replace(TINY, init=" ")


def test_auto_takes_the_shipped_start_of_the_shape_or_says_there_is_none(tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(pretrained, "SHIPPED_DIR", tmp_path)
    assert resolve_detector_start(TINY) == (None, "random weights: no detector start is shipped for this network "
                                                  f"shape ({shipped_detector_start(TINY).name})")
    path, _ = _start(tmp_path)
    path.rename(shipped_detector_start(TINY))
    start, line = resolve_detector_start(TINY)
    assert start is not None and line.startswith("the shipped detector start detector-start-")
    assert resolve_detector_start(replace(TINY, init="none")) == (None, "random weights (detector.init 'none')")


def test_the_demos_detector_has_a_shipped_start() -> None:
    """The repository ships the start the demo's detector takes by default, and it fits that network."""
    start, line = resolve_detector_start(DEMO_DETECTOR)
    assert start is not None, line
    apply_start(build_detector(DEMO_DETECTOR, 6), start)


def test_from_scratch_starts_the_demos_detector_from_random_weights_too() -> None:
    quick = DEMO_SIZES["quick"].pipeline
    assert quick.detector.init == "auto"
    scratch = quick.with_init("none")
    assert scratch.detector.init == "none" and scratch.config.train.init == "none"
    assert quick.with_init("some/pose-start.pt").detector.init == "auto"  # a pose start is no detector's


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("detector_start") / "scenes"
    assert trainer(["render", "--objects", "builtin", "--out", str(out), "--scenes", "4", "--size", "128", "96",
                    "--seed", "7", "--quiet"]) == 0
    return out


def test_training_from_a_start_records_it_in_the_exported_detector(scenes: Path, tmp_path: Path, capsys) -> None:
    path, _ = _start(tmp_path)
    settings = [f"detector.{key}={value}" for key, value in
                (("input_width", 128), ("input_height", 96), ("widths", "[8, 8, 16, 16, 16]"), ("fpn_channels", 32),
                 ("head_convs", 1), ("batch_size", 4), ("val_fraction", 0.25), ("epochs", 1))]
    argv = ["train-detector", "--split", str(scenes), "--quiet", *(item for s in settings for item in ("--set", s))]
    assert trainer([*argv, "--out", str(tmp_path / "run"), "--set", f'detector.init="{path}"']) == 0
    assert f"first weights from the detector start {path}" in capsys.readouterr().out
    training = Detector(tmp_path / "run" / "detector.onnx").metadata.training
    assert training["first_weights"].startswith(f"the detector start {path}")
    assert trainer([*argv, "--out", str(tmp_path / "scratch"), "--from-scratch"]) == 0
    assert "first weights from random weights (detector.init 'none')" in capsys.readouterr().out
