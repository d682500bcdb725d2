"""Token id <-> factor conversion (docs/formats.md §2): factor k = (t // V^k) % V, t = sum_k f_k * V^k; the bits of
a factor value."""
from typing import Optional

import torch


def factorize_token_ids(token_ids: torch.Tensor, num_factored_vocabs: int = 2,
                        factored_vocab_size: int = 512) -> torch.Tensor:
    """(...,) int token ids -> (..., F) factor ids, factor 0 the least significant."""
    powers = factored_vocab_size ** torch.arange(num_factored_vocabs, device=token_ids.device)
    return (token_ids.unsqueeze(-1) // powers) % factored_vocab_size


def unfactorize_token_ids(factor_ids: torch.Tensor, num_factored_vocabs: int = 2,
                          factored_vocab_size: int = 512) -> torch.Tensor:
    """(..., F) factor ids -> (...,) token ids."""
    assert factor_ids.size(-1) == num_factored_vocabs
    powers = factored_vocab_size ** torch.arange(num_factored_vocabs, device=factor_ids.device)
    return (factor_ids * powers).sum(-1)


def bits_of_power_of_two(size: int) -> Optional[int]:
    """J where size = 2^J >= 2 (the bits of an id below it: 18 for the 2^18 LFQ codes), None for any other size."""
    num_bits = size.bit_length() - 1
    return num_bits if size > 1 and 1 << num_bits == size else None


def factor_value_bits(factored_vocab_size: int, device=None) -> torch.Tensor:
    """(V, J) float: bit j (least significant first) of every factor value v < V = 2^J. With V a power of two, a
    token's id bits are its factors' bits in factor order, so these are the LFQ code's signs (docs/formats.md §2)."""
    num_bits = bits_of_power_of_two(factored_vocab_size)
    if num_bits is None:
        raise ValueError(f"factor value bits need a power-of-two factored vocabulary, got {factored_vocab_size}")
    values_V1 = torch.arange(factored_vocab_size, device=device).unsqueeze(-1)
    return ((values_V1 >> torch.arange(num_bits, device=device)) & 1).float()
