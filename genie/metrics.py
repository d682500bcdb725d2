"""Challenge metrics on tensors (docs/formats.md §5), shared by STMaskGIT's loss, evaluate.py and the benchmark."""
from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from einops import rearrange

from genie.factorization import factorize_token_ids


def factored_cross_entropy(logits_BVF: torch.Tensor, targets_B: torch.Tensor) -> torch.Tensor:
    """Per-token cross entropy summed over the factors.

    logits_BVF: (B, V, F, *dims) factored logits, factor 0 the least significant.
    targets_B: (B, *dims) token ids in [0, V**F).
    Returns (B, *dims) float: sum over factors k of -log softmax(logits[:, :, k])[factor_k(target)].
    """
    V, F_ = logits_BVF.shape[1], logits_BVF.shape[2]
    if logits_BVF.shape[:1] + logits_BVF.shape[3:] != targets_B.shape:
        raise ValueError(f"logits {tuple(logits_BVF.shape)} (B, V, F, ...) do not match targets "
                         f"{tuple(targets_B.shape)} (B, ...)")
    factors_BF = torch.movedim(factorize_token_ids(targets_B, F_, V), -1, 1)
    return F.cross_entropy(logits_BVF.float(), factors_BF, reduction="none").sum(dim=1)


def factored_argmax_correct(logits_BVF: torch.Tensor, targets_B: torch.Tensor) -> torch.Tensor:
    """(B, *dims) bool: the argmax of every factor equals the target's factor."""
    V, F_ = logits_BVF.shape[1], logits_BVF.shape[2]
    factors_BF = torch.movedim(factorize_token_ids(targets_B, F_, V), -1, 1)
    return (logits_BVF.argmax(dim=1) == factors_BF).all(dim=1)


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
