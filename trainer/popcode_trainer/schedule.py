"""The learning rate over a run, as a function of training progress (so a resumed run continues exactly).

``constant`` is the paper's (Adam at a fixed rate). ``cosine`` decays the rate
from ``lr`` to zero along half a cosine over the run, the usual schedule for a
fixed budget: large steps early, small ones to settle at the end. Either may
start with a linear warm-up over ``warmup_epochs``.
"""

from __future__ import annotations

import math

SCHEDULES = ("constant", "cosine")


def learning_rate(lr: float, schedule: str, epoch_progress: float, epochs: int, warmup_epochs: float = 0.0) -> float:
    """The rate at ``epoch_progress`` epochs into a run of ``epochs`` (e.g. 2.5: half-way through epoch 3)."""
    if schedule not in SCHEDULES:
        raise ValueError(f"unknown schedule {schedule!r}")
    if warmup_epochs > 0 and epoch_progress < warmup_epochs:
        return lr * epoch_progress / warmup_epochs
    if schedule == "constant":
        return lr
    decay = (epoch_progress - warmup_epochs) / max(epochs - warmup_epochs, 1e-9)
    return lr * 0.5 * (1.0 + math.cos(math.pi * min(max(decay, 0.0), 1.0)))
