"""The learning rate over a run, as a function of training progress (so a resumed run continues exactly).

``constant`` is the paper's (Adam at a fixed rate). ``cosine`` decays the rate
from ``lr`` to zero along half a cosine over the run, the usual schedule for a
fixed budget: large steps early, small ones to settle at the end. ``anneal``
keeps the rate constant and decays it linearly to zero over the last
``ANNEAL_SHARE`` of the run only, so a short budget keeps its large steps, and
the rate of the early epochs does not depend on the run's length (which the
demo's time budget needs: it fixes the length after the first epoch). Each may
start with a linear warm-up over ``warmup_epochs``.
"""

from __future__ import annotations

import math

SCHEDULES = ("constant", "cosine", "anneal")
ANNEAL_SHARE = 0.2


def learning_rate(lr: float, schedule: str, epoch_progress: float, epochs: int, warmup_epochs: float = 0.0) -> float:
    """The rate at ``epoch_progress`` epochs into a run of ``epochs`` (e.g. 2.5: half-way through epoch 3)."""
    if schedule not in SCHEDULES:
        raise ValueError(f"unknown schedule {schedule!r}")
    if warmup_epochs > 0 and epoch_progress < warmup_epochs:
        return lr * epoch_progress / warmup_epochs
    if schedule == "constant":
        return lr
    if schedule == "anneal":
        return lr * min(max((epochs - epoch_progress) / (ANNEAL_SHARE * epochs), 0.0), 1.0)
    decay = (epoch_progress - warmup_epochs) / max(epochs - warmup_epochs, 1e-9)
    return lr * 0.5 * (1.0 + math.cos(math.pi * min(max(decay, 0.0), 1.0)))


def first_epoch_rate_is_fixed(schedule: str, shortest_run: int) -> bool:
    """Whether the rate through the first epoch is the same for every run of at least ``shortest_run`` epochs."""
    if schedule == "anneal":
        return (1.0 - ANNEAL_SHARE) * shortest_run >= 1.0
    return schedule == "constant"
