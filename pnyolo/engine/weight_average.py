"""An exponential moving average of a model's weights, the model that validation, checkpoints and
evaluation use when ``train.ema_decay`` > 0 (as YOLO trainers do: the average of the last few
hundred steps' weights is smoother than the last step's)."""
from __future__ import annotations

import copy

import torch
from torch import nn


class WeightAverage:
    """``average = d * average + (1 - d) * weights`` after each optimizer step, for every
    floating-point parameter and buffer (batch-norm running statistics); integer buffers are copied.

    ``d`` warms up as ``min(decay, (1 + n) / (10 + n))`` after ``n`` updates, so the early average
    follows the fast-changing weights instead of remembering their random start.
    """

    def __init__(self, model: nn.Module, decay: float, updates: int = 0):
        if not 0 < decay < 1:
            raise ValueError(f"decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.updates = updates
        self.model = copy.deepcopy(model)
        for p in self.model.parameters():
            p.requires_grad_(False)
        self._state = self.model.state_dict()  # views of the average's tensors (load_state_dict copies into them)

    def current_decay(self) -> float:
        return min(self.decay, (1 + self.updates) / (10 + self.updates))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = self.current_decay()
        for name, value in model.state_dict().items():
            if value.is_floating_point():
                self._state[name].lerp_(value, 1.0 - d)
            else:
                self._state[name].copy_(value)
