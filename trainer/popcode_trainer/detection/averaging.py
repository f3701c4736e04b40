"""An exponential moving average of a detector's weights: the weights validated and exported when
``detector.ema_decay`` is set (issue 61: a detector trained from scratch on few scenes has a noisy last step; the
average of its recent steps is a cheaper ensemble than another epoch; its curve beside the raw weights' in
bench/results/shipped-detector.md).
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn


class WeightAverage:
    """The moving average of ``model``'s parameters and batch-norm statistics, updated after each optimiser step.

    The decay ramps up as ``(1 + n) / (10 + n)`` until it reaches ``decay``, so the first steps do not hold the
    random first weights in the average for thousands of steps."""

    def __init__(self, model: nn.Module, decay: float, state: dict[str, Any] | None = None) -> None:
        self.model = copy.deepcopy(model).eval()
        for parameter in self.model.parameters():
            parameter.requires_grad_(False)
        self.decay, self.updates = decay, 0
        if state is not None:
            self.model.load_state_dict(state["weights"])
            self.updates = int(state["updates"])

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        decay = min(self.decay, (1 + self.updates) / (10 + self.updates))
        for averaged, current in zip(self.model.state_dict().values(), model.state_dict().values(), strict=True):
            if averaged.dtype.is_floating_point:
                averaged.mul_(decay).add_(current.detach(), alpha=1.0 - decay)
            else:  # batch norm's step counter
                averaged.copy_(current)

    def state(self) -> dict[str, Any]:
        """What a checkpoint keeps of the average (a resumed run goes on averaging from it)."""
        return {"weights": self.model.state_dict(), "updates": self.updates}
