"""The factored token losses (docs/formats.md §5), shared by STMaskGIT's loss and the evaluation."""
import torch
import torch.nn.functional as F

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
