"""A checkpoint trained in seconds (the tiny configuration) and a frame to check its export on, for the export,
command and torch-engine tests alike."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from synthetic import draw
from tiny import tiny_config, tiny_data, tiny_representation

from popcode_trainer.train.loop import train
from popcode_trainer.train.run_files import LAST_CHECKPOINT


def trained_checkpoint(tmp_path: Path, **train_settings: Any) -> tuple[Path, np.ndarray]:
    """The last checkpoint of one tiny epoch in ``tmp_path/run`` and the crops it held out for validation."""
    config = tiny_config(tmp_path / "run", epochs=1, **train_settings)
    rep = tiny_representation(config)
    train_set, val_set = tiny_data(rep)
    train(config, rep, train_set, val_set, val_instances=val_set.instances)
    crops = np.stack([val_set[i]["image"].numpy() for i in range(len(val_set))])
    return tmp_path / "run" / LAST_CHECKPOINT, crops


def pasted_frame() -> tuple[np.ndarray, list[tuple[float, ...]]]:
    """A full frame with the drawn object pasted at several places (so the allocentric conversion matters)
    and the boxes whose crops are exactly the pasted squares."""
    frame = np.zeros((480, 640), np.float32)
    boxes = []
    for i, (x, y) in enumerate([(20, 30), (300, 200), (500, 340)]):
        R = np.linalg.qr(np.random.default_rng(i).normal(size=(3, 3)))[0]
        R *= np.linalg.det(R)
        frame[y : y + 128, x : x + 128] = draw(R)
        boxes.append((x + 5.8, y + 5.8, 116.4, 116.4))  # padding 1.1 -> a 128 px square: crops are exact
    return frame, boxes
