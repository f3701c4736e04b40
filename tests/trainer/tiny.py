"""A tiny configuration (small network, 42 x 12 code) that trains in seconds on a CPU."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from symmetry_cases import CASES
from synthetic import RotatedPoints

from popcode_trainer.train.config import Config
from popcode_trainer.train.representations import OutputRepresentation, build_representation


def tiny_config(out_dir: Path, **train: Any) -> Config:
    return Config.from_dict({
        "data": {"num_workers": 0},
        "code": {"n_axes": 42, "n_angles": 12, "sigma_deg": 30.0},
        "network": {"conv_channels": [8, 8, 8], "squeeze_channels": 4, "hidden": [32, 32, 32]},
        "train": {"epochs": 2, "batch_size": 16, "lr": 1e-3, "out_dir": str(out_dir), "device": "cpu",
                  "num_hypotheses": 4, **train},
    })


def tiny_representation(config: Config, case: str = "none") -> OutputRepresentation:
    code, cfg = config.code, config.train
    return build_representation(cfg.representation, {1: CASES[case]}, code.n_axes, code.n_angles, code.sigma_deg,
                                cfg.rotation_frame, cfg.num_hypotheses, loss=cfg.loss)


def tiny_data(representation: OutputRepresentation, train_count: int = 64,
              val_count: int = 16) -> tuple[RotatedPoints, RotatedPoints]:
    return (RotatedPoints(train_count, representation.target, seed=1),
            RotatedPoints(val_count, representation.target, seed=2))
