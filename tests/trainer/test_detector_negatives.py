"""Frames without parts (``render --scenes --empty-share``, and generated ones: ``detector.negative_share``) as a
detector's negatives: read as frames with an empty target, they reach the detector's loss, a box on them is a
false positive, and the pose models' training finds no crop in them."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from popcode_trainer.cli import main as trainer
from popcode_trainer.detection.config import DetectorConfig
from popcode_trainer.detection.frames import FrameSet, collate, negative_frame, read_frames
from popcode_trainer.detection.network import build_detector
from popcode_trainer.train.checkpoint import load

OBJ_IDS = [1, 2, 3, 4, 5, 6]
SMALL = DetectorConfig(input_width=128, input_height=96, widths=(8, 8, 16, 16, 16), fpn_channels=32, head_convs=1,
                       batch_size=2, val_fraction=0.25, epochs=1, init="none")


@pytest.fixture(scope="module")
def split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four bin scenes of the built-in parts at 128 x 96, images 1 and 3 without parts (3 also without
    distractors)."""
    out = tmp_path_factory.mktemp("negatives") / "scenes"
    assert trainer(["render", "--objects", "builtin", "--out", str(out), "--scenes", "4", "--size", "128", "96",
                    "--seed", "4", "--empty-share", "0.5", "--quiet"]) == 0
    return out


def test_frames_without_parts_are_frames_with_an_empty_target(split: Path) -> None:
    frames = read_frames([split], OBJ_IDS, SMALL)
    assert [frame.key[2] for frame in frames] == [0, 1, 2, 3]
    assert [len(frame.boxes) > 0 for frame in frames] == [True, False, True, False]
    _, target = FrameSet(frames, SMALL, augment=True, progress=False)[1]
    assert target["boxes"].shape == (0, 4) and target["labels"].shape == (0,)


def test_a_batch_of_empty_frames_teaches_background_only(split: Path) -> None:
    """Every place of an empty frame is background: a finite classification loss, nothing to regress."""
    frames = read_frames([split], OBJ_IDS, SMALL)
    empty = FrameSet([frame for frame in frames if not len(frame.boxes)], SMALL, augment=True, progress=False)
    torch.manual_seed(0)
    model = build_detector(SMALL, len(OBJ_IDS)).train()
    losses = model(*collate([empty[0], empty[1]]))
    assert math.isfinite(losses["classification"].item()) and losses["classification"].item() > 0
    assert losses["bbox_regression"].item() == 0 and losses["bbox_ctrness"].item() == 0
    losses["classification"].backward()
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in model.parameters())


def test_train_detector_trains_on_every_frame_empty_ones_too(split: Path, tmp_path: Path) -> None:
    sizes = [f"detector.{key}={value}" for key, value in (
        ("input_width", 128), ("input_height", 96), ("widths", "[8, 8, 16, 16, 16]"), ("fpn_channels", 32),
        ("head_convs", 1), ("batch_size", 2), ("val_fraction", 0.25), ("epochs", 1), ("init", '"none"'))]
    assert trainer(["train-detector", "--split", str(split), "--out", str(tmp_path / "run"), "--quiet",
                    *[arg for setting in sizes for arg in ("--set", setting)]]) == 0
    frames = load(tmp_path / "run" / "detector.pt")["frames"]
    assert (frames["train"], frames["val"]) == (3, 1)


@pytest.mark.filterwarnings("ignore:.*symmetric poses are closer")  # the tiny code's coarse grid: not tested here
def test_pose_training_ignores_frames_without_parts(split: Path, tmp_path: Path) -> None:
    """The pose models train on crops of parts: an image without parts gives none and breaks nothing."""
    settings = {"data.splits": f'["{split}"]', "data.models_dir": f'"{split / "models"}"',
                "data.obj_ids": "[3, 4, 5, 6]", "data.val_fraction": 0, "data.min_visib_fract": 0.3,
                "data.num_workers": 0, "code.n_axes": 42, "code.n_angles": 8, "network.conv_channels": "[4, 4, 4]",
                "network.hidden": "[8, 8, 8]", "train.epochs": 1, "train.batch_size": 4, "train.init": '"none"',
                "train.compile": '"off"', "train.out_dir": f'"{tmp_path / "run"}"'}
    assert trainer(["train", *[arg for key, value in settings.items() for arg in ("--set", f"{key}={value}")]]) == 0
    assert (tmp_path / "run" / "last.pt").is_file()


def test_generated_negatives_replace_a_share_of_the_training_frames(split: Path) -> None:
    """``detector.negative_share``: that share of the training frames (drawn per epoch) becomes a generated frame
    without parts, its target empty; validation frames stay as rendered."""
    frames = [frame for frame in read_frames([split], OBJ_IDS, SMALL) if len(frame.boxes)] * 20
    config = dataclasses.replace(SMALL, negative_share=0.5)
    generated = [len(FrameSet(frames, config, augment=True, progress=False)[i][1]["boxes"]) == 0
                 for i in range(len(frames))]
    assert 0.3 < np.mean(generated) < 0.7
    assert not any(len(FrameSet(frames, SMALL, augment=True, progress=False)[i][1]["boxes"]) == 0
                   for i in range(len(frames)))  # share 0: every frame keeps its parts (a zoom keeps at least one)
    assert all(len(FrameSet(frames, config, augment=False, progress=False)[i][1]["boxes"])
               for i in range(len(frames)))


def test_a_generated_negative_is_a_frame_of_every_kind() -> None:
    rng = np.random.default_rng(0)
    negatives = [negative_frame((96, 128), rng) for _ in range(40)]
    assert all(n.shape == (96, 128) and n.dtype == np.float32 and 0 <= n.min() <= n.max() <= 1 for n in negatives)
    spreads = sorted(float(n.std()) for n in negatives)
    assert spreads[0] == 0.0 and spreads[-1] > 0.05  # flat levels and noisy or graded frames
    assert len({round(float(n.mean()), 2) for n in negatives}) > 20  # at many levels


@pytest.mark.parametrize("setting", ["detector.negative_share=0.95", "detector.negative_share=-0.1",
                                     "detector.ema_decay=1", "detector.ema_decay=-0.5"])
def test_out_of_range_negatives_and_averages_are_refused(split: Path, tmp_path: Path, capsys, setting: str) -> None:
    assert trainer(["train-detector", "--split", str(split), "--out", str(tmp_path / "run"), "--set", setting]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and setting.split("=")[0].split(".")[1] in error
