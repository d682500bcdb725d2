"""Lookup-free quantization (MAGVIT2): each latent channel is quantized to -1 or +1, one bit of the token id.

Bit order (docs/formats.md §2): channel c is +1 exactly when bit c of the token id is set, t = sum_c [z_c > 0] * 2^c.

Entropy loss, as Open-MAGVIT2 defines it: for a latent z (C channels) the code distribution is
p(k) = softmax_k(2 <z, code_k> / T) over the 2^C codes (code_k in {-1, +1}^C; the same as softmax(-||z - code_k||^2 / T)
because ||code_k||^2 is constant), and
    entropy_loss = mean_n H(p_n) - H_eps(mean_n p_n),    H_eps(a) = -sum_k a_k log(a_k + eps),  eps = 1e-5.
Computed naively this needs an (N, 2^C) tensor (2 GiB in fp32 for N = 2048, C = 18). Here it is exact without one:
- p_n is a product over channels: p_n(k) = prod_c q_nc(bit_c(k)) with q_nc(1) = sigmoid(4 z_nc / T), so H(p_n) is the
  sum of C binary entropies.
- Split the bits into a low group (channels 0..g-1) and a high group (g..C-1). p_n(k) = P_lo[n, k_lo] * P_hi[n, k_hi]
  with P_lo (N, 2^g) and P_hi (N, 2^(C-g)) the group distributions, so the batch average over all 2^C codes is one
  matrix product, mean_n p_n = P_lo^T @ P_hi / N, a (2^g, 2^(C-g)) matrix with k = k_lo + 2^g * k_hi.
  Peak memory is O(N * 2^(C/2) + 2^C) instead of O(N * 2^C): about 4 MiB + 1 MiB for N = 2048, C = 18.
"""
from dataclasses import dataclass
from typing import Optional, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F
from einops import rearrange

# 2^26 codes = 256 MiB for the averaged distribution; beyond that the codebook entropy itself is unaffordable
MAX_ENTROPY_CHANNELS = 26


def ids_to_bits(token_ids: torch.Tensor, num_bits: int) -> torch.Tensor:
    """(...,) integer token ids -> (..., num_bits) bool, last axis c = bit c (channel c)."""
    shifts = torch.arange(num_bits, device=token_ids.device)
    return ((token_ids.long().unsqueeze(-1) >> shifts) & 1).bool()


def bits_to_ids(bits: torch.Tensor) -> torch.Tensor:
    """(..., C) bool / {0, 1} bits, last axis c = bit c -> (...,) int64 token ids."""
    shifts = torch.arange(bits.shape[-1], device=bits.device)
    return (bits.long() << shifts).sum(-1)


def ids_to_latents(token_ids_BHW: torch.Tensor, num_channels: int, dtype=torch.float32) -> torch.Tensor:
    """(B, h, w) token ids -> quantized latents (B, C, h, w) of +-1, the decoder's input."""
    bits_BHWC = ids_to_bits(token_ids_BHW, num_channels)
    return rearrange(bits_BHWC.to(dtype) * 2 - 1, "B H W C -> B C H W")


def latents_to_ids(z_BCHW: torch.Tensor) -> torch.Tensor:
    """(B, C, h, w) latents -> (B, h, w) int64 token ids: bit c set iff channel c > 0."""
    return bits_to_ids(rearrange(z_BCHW > 0, "B C H W -> B H W C"))


def _at_least_fp32(x: torch.Tensor) -> torch.Tensor:
    return x if x.dtype == torch.float64 else x.float()


def binary_entropy_from_logits(a: torch.Tensor) -> torch.Tensor:
    """Entropy (nats) of Bernoulli(sigmoid(a)), elementwise, stable for large |a|."""
    q = torch.sigmoid(a)
    return -(q * F.logsigmoid(a) + (1 - q) * F.logsigmoid(-a))


def _group_code_probs(a_NG: torch.Tensor) -> torch.Tensor:
    """Product distribution of G independent bits with logits a (N, G) -> (N, 2^G) over the group's codes."""
    G = a_NG.shape[-1]
    bits_KG = ids_to_bits(torch.arange(2 ** G, device=a_NG.device), G).to(a_NG.dtype)
    # softmax_k(sum_c bit_kc a_c) = prod_c sigmoid(a_c)^bit_kc * (1 - sigmoid(a_c))^(1 - bit_kc)
    return torch.softmax(a_NG @ bits_KG.T, dim=-1)


def entropy_terms(z_NC: torch.Tensor, temperature: float = 0.01,
                  eps: float = 1e-5) -> Tuple[torch.Tensor, torch.Tensor]:
    """Exact (per_sample_entropy, codebook_entropy) of the LFQ code distribution, without an (N, 2^C) tensor.

    z_NC: (N, C) continuous latents (one row per spatial position). Both results are scalars in nats; the entropy
    loss is per_sample_entropy - codebook_entropy. Computed in fp32 with autocast off.
    """
    N, C = z_NC.shape
    if C > MAX_ENTROPY_CHANNELS:
        raise ValueError(f"LFQ codebook entropy over 2^{C} codes is not affordable "
                         f"(at most {MAX_ENTROPY_CHANNELS} channels)")
    with torch.autocast(device_type=z_NC.device.type, enabled=False):
        a_NC = 4.0 * _at_least_fp32(z_NC) / temperature  # logit of bit c being 1
        per_sample_entropy = binary_entropy_from_logits(a_NC).sum(-1).mean()
        g = (C + 1) // 2
        P_lo = _group_code_probs(a_NC[:, :g])  # (N, 2^g)
        P_hi = _group_code_probs(a_NC[:, g:])  # (N, 2^(C-g))
        avg_probs = P_lo.T @ P_hi / N  # (2^g, 2^(C-g)): the batch-averaged distribution over all 2^C codes
        codebook_entropy = -(avg_probs * torch.log(avg_probs + eps)).sum()
    return per_sample_entropy, codebook_entropy


def naive_entropy_terms(z_NC: torch.Tensor, temperature: float = 0.01,
                        eps: float = 1e-5) -> Tuple[torch.Tensor, torch.Tensor]:
    """Reference: the same quantities from the full (N, 2^C) distribution. For tests and benchmarks only."""
    C = z_NC.shape[-1]
    z_NC = _at_least_fp32(z_NC)
    codes_KC = ids_to_bits(torch.arange(2 ** C, device=z_NC.device), C).to(z_NC.dtype) * 2 - 1
    logits_NK = 2 * z_NC @ codes_KC.T / temperature
    probs_NK = torch.softmax(logits_NK, dim=-1)
    per_sample_entropy = -(probs_NK * torch.log_softmax(logits_NK, dim=-1)).sum(-1).mean()
    avg_probs_K = probs_NK.mean(0)
    codebook_entropy = -(avg_probs_K * torch.log(avg_probs_K + eps)).sum()
    return per_sample_entropy, codebook_entropy


def naive_entropy_loss(z_NC: torch.Tensor, temperature: float = 0.01, eps: float = 1e-5) -> torch.Tensor:
    """Reference entropy loss (per-sample minus codebook entropy) built on an (N, 2^C) tensor."""
    per_sample_entropy, codebook_entropy = naive_entropy_terms(z_NC, temperature, eps)
    return per_sample_entropy - codebook_entropy


@dataclass
class LFQOutput:
    """What the quantizer returns. Losses are 0-dim tensors (zeros when losses were not computed)."""
    zq: torch.Tensor  # (B, C, h, w) +-1 in the forward pass, straight-through gradient to z
    token_ids: torch.Tensor  # (B, h, w) int64
    commit_loss: torch.Tensor  # mean (z - sign(z))^2
    entropy_loss: torch.Tensor  # per_sample_entropy - codebook_entropy
    per_sample_entropy: torch.Tensor
    codebook_entropy: torch.Tensor


class LFQ(nn.Module):
    """Lookup-free quantizer over `num_channels` binary channels (codebook of 2^num_channels implicit codes).

    No parameters and no buffers, so checkpoints have no `quantizer.*` keys.
    """

    def __init__(self, num_channels: int, entropy_temperature: float = 0.01, eps: float = 1e-5):
        super().__init__()
        self.num_channels = num_channels
        self.entropy_temperature = entropy_temperature
        self.eps = eps

    @property
    def codebook_size(self) -> int:
        return 2 ** self.num_channels

    def forward(self, z_BCHW: torch.Tensor, compute_losses: Optional[bool] = None) -> LFQOutput:
        """Quantize latents (B, C, h, w). Losses are computed when `compute_losses` (default: in training mode)."""
        if z_BCHW.ndim != 4 or z_BCHW.shape[1] != self.num_channels:
            raise ValueError(f"LFQ expects latents (B, {self.num_channels}, h, w), got {tuple(z_BCHW.shape)}")
        compute_losses = self.training if compute_losses is None else compute_losses
        hard_BCHW = torch.where(z_BCHW > 0, 1.0, -1.0).to(z_BCHW.dtype)
        zq_BCHW = z_BCHW + (hard_BCHW - z_BCHW).detach()
        token_ids = latents_to_ids(z_BCHW)
        zero = z_BCHW.new_zeros((), dtype=torch.float32)
        commit_loss = per_sample_entropy = codebook_entropy = zero
        if compute_losses:
            commit_loss = F.mse_loss(z_BCHW.float(), hard_BCHW.float())
            z_NC = rearrange(z_BCHW, "B C H W -> (B H W) C")
            per_sample_entropy, codebook_entropy = entropy_terms(z_NC, self.entropy_temperature, self.eps)
        return LFQOutput(zq=zq_BCHW, token_ids=token_ids, commit_loss=commit_loss,
                         entropy_loss=per_sample_entropy - codebook_entropy,
                         per_sample_entropy=per_sample_entropy, codebook_entropy=codebook_entropy)

    def extra_repr(self) -> str:
        return f"num_channels={self.num_channels}, entropy_temperature={self.entropy_temperature}"
