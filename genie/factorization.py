"""Token id <-> factor conversion (docs/formats.md §2): factor k = (t // V^k) % V, t = sum_k f_k * V^k."""
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


