"""Evaluation helpers on tensors: token accuracy, images scaled for LPIPS, running means."""
from dataclasses import dataclass
from typing import Optional

import torch
from einops import rearrange


def token_accuracy(samples: torch.Tensor, targets: torch.Tensor) -> float:
    """Fraction of tokens where the sampled id equals the target id (same shapes)."""
    if samples.shape != targets.shape:
        raise ValueError(f"samples {tuple(samples.shape)} and targets {tuple(targets.shape)} differ in shape")
    return (samples == targets).float().mean().item()


def images_to_unit_range(images_NHW3: torch.Tensor) -> torch.Tensor:
    """uint8 (N, H, W, 3) images -> float (N, 3, H, W) in [-1, 1], the range LPIPS expects."""
    return rearrange(images_NHW3, "N H W c -> N c H W").float() / 127.5 - 1


@dataclass
class RunningMean:
    """Sum and count of a metric; `mean` is None until something was added."""
    total: float = 0.0
    count: int = 0

    def update(self, value_sum: float, count: int = 1) -> None:
        self.total += float(value_sum)
        self.count += count

    @property
    def mean(self) -> Optional[float]:
        return self.total / self.count if self.count else None
