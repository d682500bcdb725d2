"""The MaskGIT mask schedule, shared by the training collator and the sampler."""
import math

import torch


def cosine_schedule(u):
    """Fraction of tokens left masked at progress u in [0, 1]: cos(pi/2 * u) (1 at u=0, 0 at u=1)."""
    if isinstance(u, torch.Tensor):
        return torch.cos(u * math.pi / 2)
    return math.cos(u * math.pi / 2)


def num_masked_after_step(step: int, num_steps: int, num_tokens: int) -> int:
    """Tokens that stay masked after MaskGIT step `step` (0-based) of `num_steps`: ceil(cos(pi/2 (s+1)/n) * S).

    The last step leaves none masked.
    """
    if step + 1 >= num_steps:  # cos(pi/2) * S is 1e-14, not 0: the last step always reveals everything
        return 0
    return math.ceil(cosine_schedule((step + 1) / num_steps) * num_tokens)
