"""Opt-in previous-frame pointer (GenieConfig.copy_radius): a token may be copied from the previous frame.

Most of what a camera sees one step later was already in view, shifted. A small model cannot reproduce an exact
18-bit token through its 2 x 512-way readout (d_model is far below 512, so it has no room for an identity map), so
it learns a blurred average instead and ends up below simply copying. The pointer gives the copy a direct path:
for each predicted position the hidden state scores K = (2r+1)^2 neighbours of the same position in frame t-1
(offsets up to r tokens in each direction) and one "new token" option; the prediction is the mixture

    p_f(v) = w_new * softmax(readout_f)(v) + sum_k w_k [factor_f(neighbour_k) == v]     (w = softmax(scores))

for each factor f, returned as log-probabilities, which every consumer of factored logits (cross entropy, argmax,
softmax and temperature in the sampler) treats like logits. Neighbours outside the frame, and masked ones, are
not offered; with none left (frame 0) the prediction is the readout alone. Docs: docs/formats.md §3.

Opt-in on top (copy_match_input): every known token's input embedding also gets a learned embedding of which of
its K previous-frame neighbours hold the same token. That is token-level motion evidence (where the content at this
position came from in the last step), which a spatio-temporal transformer, attending over time only at the same
position, otherwise has to infer through several layers.
"""
from typing import Optional

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from genie.factorization import factorize_token_ids


class CopyHead(nn.Module):
    def __init__(self, d_model: int, radius: int, num_factored_vocabs: int, factored_vocab_size: int,
                 mask_token_id: int, match_input: bool = False):
        super().__init__()
        self.radius = radius
        self.num_factored_vocabs = num_factored_vocabs
        self.factored_vocab_size = factored_vocab_size
        self.mask_token_id = mask_token_id
        side = 2 * radius + 1
        self.num_sources = side * side
        # scores of the K neighbours (row-major offsets, (-r, -r) first) and, last, of a new token
        self.score_proj = nn.Linear(d_model, self.num_sources + 1)
        # opt-in (GenieConfig.copy_match_input): embedding of which neighbours hold a given token's own value
        self.match_proj = nn.Linear(self.num_sources, d_model, bias=False) if match_input else None

    def sources(self, prev_BTHW: torch.Tensor) -> torch.Tensor:
        """Previous-frame token ids (B, T, H, W) (mask_token_id where unknown) -> the K neighbours of every
        position (B, T, H*W, K), mask_token_id where a neighbour is outside the frame or unknown."""
        r = self.radius
        H, W = prev_BTHW.shape[-2:]
        padded = F.pad(prev_BTHW, (r, r, r, r), value=self.mask_token_id)
        neighbours = [padded[..., dy:dy + H, dx:dx + W] for dy in range(2 * r + 1) for dx in range(2 * r + 1)]
        return rearrange(torch.stack(neighbours, dim=-1), "B T H W K -> B T (H W) K")

    def match_embedding(self, x_BTHW: torch.Tensor, sources_BTSK: torch.Tensor) -> torch.Tensor:
        """Token ids (B, T, H, W) and their sources (B, T, S, K) -> (B, T, S, C): the embedding of the binary vector
        "neighbour k of the previous frame holds this token" (all zero for a masked token or an unknown frame)."""
        x_BTS1 = rearrange(x_BTHW, "B T H W -> B T (H W) 1")
        match_BTSK = (sources_BTSK == x_BTS1) & (x_BTS1 != self.mask_token_id)
        return self.match_proj(match_BTSK.to(self.match_proj.weight.dtype))

    def forward(self, logits_NVF: torch.Tensor, hidden_NC: torch.Tensor, sources_NK: torch.Tensor) -> torch.Tensor:
        """Readout logits (..., V, F), hidden states (..., C), sources (..., K) -> log-probabilities (..., V, F)."""
        V, F_ = self.factored_vocab_size, self.num_factored_vocabs
        offered_NK = sources_NK != self.mask_token_id
        scores = self.score_proj(hidden_NC).float()
        scores = scores.masked_fill(F.pad(~offered_NK, (0, 1), value=False), float("-inf"))
        log_weights = scores.log_softmax(dim=-1)
        w_copy_NK = log_weights[..., :-1].exp()
        factors_NFK = rearrange(factorize_token_ids(sources_NK.masked_fill(~offered_NK, 0), F_, V),
                                "... K F -> ... F K")
        # (F, V) layout: the readout's own memory order, so the softmax runs over contiguous rows
        log_new_NFV = (rearrange(logits_NVF, "... V F -> ... F V").float().log_softmax(dim=-1)
                       + log_weights[..., -1, None, None])
        # Only the <= K values some neighbour holds get copy mass; every other value keeps log_new. The mass of each
        # neighbour's value (the weights of all neighbours holding it) comes from a dense scatter, gathered back.
        # A dropped neighbour points at value 0 with weight 0, which leaves value 0's result unchanged.
        copy_NFV = torch.zeros_like(log_new_NFV)
        copy_NFV.scatter_add_(-1, factors_NFK, w_copy_NK.unsqueeze(-2).expand_as(factors_NFK).contiguous())
        # log(0) of a dropped neighbour's value is clamped: finite, and no gradient flows through the clamp
        mixed_NFK = torch.logaddexp(log_new_NFV.gather(-1, factors_NFK),
                                    copy_NFV.gather(-1, factors_NFK).clamp_min(1e-30).log())
        # one writer per value, so that its gradient is counted once: each value slot records one of the neighbours
        # holding it (whichever the scatter kept), and the others write to a spare column V instead
        K = factors_NFK.shape[-1]
        neighbour_NFK = torch.arange(K, device=factors_NFK.device).expand_as(factors_NFK)
        owner_NFV = torch.empty(log_new_NFV.shape, dtype=factors_NFK.dtype, device=factors_NFK.device)
        owner_NFV.scatter_(-1, factors_NFK, neighbour_NFK)  # only slots some neighbour holds are read back
        repeated_NFK = owner_NFV.gather(-1, factors_NFK) != neighbour_NFK
        out_NFV = F.pad(log_new_NFV, (0, 1))
        out_NFV.scatter_(-1, factors_NFK.masked_fill(repeated_NFK, V), mixed_NFK)
        return rearrange(out_NFV[..., :V], "... F V -> ... V F")


def previous_frames(x_BTHW: torch.Tensor, mask_token_id: int,
                    before_BHW: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The frame before each frame of x (B, T, H, W): before_BHW (the frame preceding x, None: unknown = all
    mask tokens) for the first, then x's frames 0..T-2."""
    if before_BHW is None:
        before_BHW = torch.full_like(x_BTHW[:, 0], mask_token_id)
    return torch.cat([before_BHW.unsqueeze(1), x_BTHW[:, :-1]], dim=1)
