"""An exponential moving average of a model's weights (train.py --ema_decay).

After the n-th optimizer step the average moves towards the weights by 1 - d_n, where
d_n = min(decay, (1 + n) / (10 + n)): the ramp keeps the first steps' random weights from lingering in the average
when the decay is close to 1 (at decay 0.995 it reaches the full decay after about 1,800 steps; the average then
spans about 1 / (1 - decay) = 200 steps). The average lives in a copy of the model, so it can be evaluated and saved
(`save_pretrained`) like the model itself.
"""
import copy

import torch
from torch import nn


class WeightAverage:
    """The running average of `model`'s parameters; buffers are copied once, as they are not trained."""

    def __init__(self, model: nn.Module, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"WeightAverage: decay must be in (0, 1), got {decay}")
        self.decay = decay
        self.updates = 0
        self.model = copy.deepcopy(model).eval().requires_grad_(False)

    def current_decay(self) -> float:
        """d_n of the module doc for the next update."""
        n = self.updates + 1
        return min(self.decay, (1 + n) / (10 + n))

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Move the average towards `model`'s current parameters (the same architecture as the copied model)."""
        weight = 1.0 - self.current_decay()
        for average, current in zip(self.model.parameters(), model.parameters()):
            average.lerp_(current.detach(), weight)
        self.updates += 1
