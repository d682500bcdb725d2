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
from typing import Callable, NamedTuple, Optional, Tuple

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn

from genie.factorization import factorize_token_ids, unfactorize_token_ids


class Prediction(NamedTuple):
    """A model's prediction at some positions: factored logits (..., V, F) (log-probabilities for a model with a
    copy head) and, for a copy head's mixture (`CopyHead`), what decodes it as whole tokens:

    - mode_ids, mode_probs (...): its most probable whole tokens and their probabilities (`CopyHead.mode`), which
      greedy steps take instead of the factor-wise argmax of the logits;
    - copy_log_weights (..., K + 1), copy_sources (..., K), readout_logits (..., V, F): its parts (log weights of
      the K previous-frame neighbours and, last, of a new token; the neighbours' token ids; the readout's logits),
      from which sampling steps draw whole tokens (`sample_mixture_tokens`) instead of each factor on its own.

    Layouts: `logits` and `readout_logits` share one (e.g. (B, V, F, H, W) for frames), the others put the
    positions first and their own axis last (e.g. (B, H, W) and (B, H, W, K))."""
    logits: torch.Tensor
    mode_ids: Optional[torch.Tensor] = None
    mode_probs: Optional[torch.Tensor] = None
    copy_log_weights: Optional[torch.Tensor] = None
    copy_sources: Optional[torch.Tensor] = None
    readout_logits: Optional[torch.Tensor] = None

    def map(self, logits_fn: Callable[[torch.Tensor], torch.Tensor],
            positions_fn: Callable[[torch.Tensor], torch.Tensor]) -> "Prediction":
        """A `Prediction` with logits_fn applied to the fields in the logits' layout and positions_fn to the
        others (None fields stay None)."""
        return Prediction(*(None if v is None else (logits_fn if name in LOGITS_LAYOUT else positions_fn)(v)
                            for name, v in zip(self._fields, self)))


LOGITS_LAYOUT = ("logits", "readout_logits")


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
        # decoding settings, not weights (STMaskGIT.set_decoding): added to every
        # neighbour's score; whether `mode`'s copies take the single most weighted neighbour
        self.copy_bias = 0.0
        self.best_neighbour_copies = False

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

    def log_weights(self, hidden_NC: torch.Tensor, offered_NK: torch.Tensor) -> torch.Tensor:
        """Hidden states (..., C) and which neighbours are offered (..., K) -> log mixture weights (..., K + 1) of
        the K neighbours and, last, of a new token (copy_bias added to the neighbours' scores)."""
        scores = self.score_proj(hidden_NC).float()
        if self.copy_bias:
            scores = torch.cat([scores[..., :-1] + self.copy_bias, scores[..., -1:]], dim=-1)
        scores = scores.masked_fill(F.pad(~offered_NK, (0, 1), value=False), float("-inf"))
        return scores.log_softmax(dim=-1)

    def forward(self, logits_NVF: torch.Tensor, hidden_NC: torch.Tensor, sources_NK: torch.Tensor) -> torch.Tensor:
        """Readout logits (..., V, F), hidden states (..., C), sources (..., K) -> log-probabilities (..., V, F)."""
        return self._mixture(*self._parts(logits_NVF, hidden_NC, sources_NK))

    @torch.no_grad()
    def mode(self, logits_NVF: torch.Tensor, hidden_NC: torch.Tensor,
             sources_NK: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """The mixture's most probable whole token at each position and its probability: (ids (...), probs (...)).

        `forward` returns the mixture's marginal distribution of each factor. Their factor-wise argmax is the mode
        of a product distribution (the readout alone), but not of a mixture: with the weight spread over
        neighbours, the low factor of one neighbour's token and the high factor of another's can each win, giving a
        token that no option proposed (on the sample world a sixth of the greedy tokens of a rollout). The
        mixture gives token c the probability w_new * prod_f softmax(readout_f)(c_f) + sum_k w_k [neighbour_k = c],
        so its mode is one of the offered neighbours' tokens or the readout's own factor-wise mode (every other
        token has no copy mass and a lower readout probability).

        With best_neighbour_copies set (a decoding setting, STMaskGIT.set_decoding), the mode still decides
        between a copy and the readout's token, but a copy takes the token of the single most weighted neighbour
        instead of the token with the most weight summed over the neighbours holding it. The sum favours whatever
        token fills the neighbourhood, a majority filter: applied frame after frame in a rollout, it grows flat
        patches where the pointer is unsure where the content comes from. One neighbour's token is a displacement.
        """
        return self._mode(sources_NK, *self._parts(logits_NVF, hidden_NC, sources_NK))

    @torch.no_grad()
    def forward_and_mode(self, logits_NVF: torch.Tensor, hidden_NC: torch.Tensor,
                         sources_NK: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """`forward` and `mode` (inference) from one computation of their shared parts, and the log mixture
        weights (..., K + 1) (what sampling whole tokens draws the option from, genie.sampling)."""
        parts = self._parts(logits_NVF, hidden_NC, sources_NK)
        ids_N, probs_N = self._mode(sources_NK, *parts)  # first: the mixture overwrites the readout's log-probs
        log_weights = parts[1]
        return self._mixture(*parts), ids_N, probs_N, log_weights

    @torch.no_grad()
    def forward_and_log_weights(self, logits_NVF: torch.Tensor, hidden_NC: torch.Tensor,
                                sources_NK: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """`forward` and the log mixture weights (..., K + 1) (inference at a temperature: what drawing whole
        tokens needs, without `mode`'s work)."""
        parts = self._parts(logits_NVF, hidden_NC, sources_NK)
        return self._mixture(*parts), parts[1]

    def _parts(self, logits_NVF: torch.Tensor, hidden_NC: torch.Tensor, sources_NK: torch.Tensor):
        """What the mixture and its mode are computed from: which neighbours are offered (..., K), the log weights
        (..., K + 1), the neighbours' factors (..., F, K) and the readout's log-probabilities (..., F, V)."""
        V, F_ = self.factored_vocab_size, self.num_factored_vocabs
        offered_NK = sources_NK != self.mask_token_id
        factors_NFK = rearrange(factorize_token_ids(sources_NK.masked_fill(~offered_NK, 0), F_, V),
                                "... K F -> ... F K")
        # (F, V) layout: the readout's own memory order, so the softmax runs over contiguous rows
        log_new_NFV = rearrange(logits_NVF, "... V F -> ... F V").float().log_softmax(dim=-1)
        return offered_NK, self.log_weights(hidden_NC, offered_NK), factors_NFK, log_new_NFV

    def _mixture(self, offered_NK: torch.Tensor, log_weights: torch.Tensor, factors_NFK: torch.Tensor,
                 log_new_NFV: torch.Tensor) -> torch.Tensor:
        """The mixture's log-probabilities (..., V, F) from `_parts` (at inference log_new_NFV is reused in place)."""
        w_copy_NK = log_weights[..., :-1].exp()
        in_place = not torch.is_grad_enabled()  # inference: no autograd graph needs the intermediates kept
        log_new_NFV = (log_new_NFV.add_ if in_place else log_new_NFV.add)(log_weights[..., -1, None, None])
        # Only the <= K values some neighbour holds get copy mass; every other value keeps log_new. A dropped
        # neighbour points at value 0 with weight 0, which leaves value 0's result unchanged.
        mass_NFK, repeated_NFK = _mass_per_value(factors_NFK, w_copy_NK.unsqueeze(-2).expand_as(factors_NFK))
        # log(0) of a dropped neighbour's value is clamped: finite, and no gradient flows through the clamp
        mixed_NFK = torch.logaddexp(log_new_NFV.gather(-1, factors_NFK), mass_NFK.clamp_min(1e-30).log())
        if in_place:
            return rearrange(log_new_NFV.scatter_(-1, factors_NFK, mixed_NFK), "... F V -> ... V F")
        # Neighbours holding the same value write the same number into its slot; only one of them keeps its
        # gradient, so that the value's gradient is counted once.
        mixed_NFK = torch.where(repeated_NFK, mixed_NFK.detach(), mixed_NFK)
        return rearrange(log_new_NFV.scatter(-1, factors_NFK, mixed_NFK), "... F V -> ... V F")

    def _mode(self, sources_NK: torch.Tensor, offered_NK: torch.Tensor, log_weights: torch.Tensor,
              factors_NFK: torch.Tensor, log_new_NFV: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """`mode` from the sources (..., K) and `_parts`."""
        V, F_ = self.factored_vocab_size, self.num_factored_vocabs
        w_copy_NK, log_w_new_N = log_weights[..., :-1].exp(), log_weights[..., -1]
        best_log_new_NF, best_NF = log_new_NFV.max(dim=-1)
        readout_mode_N = unfactorize_token_ids(best_NF, F_, V)
        # neighbours: their copy mass (summed over the neighbours holding the same token) + the readout's share
        mass_NK = _mass_per_value(sources_NK, w_copy_NK)[0]
        log_new_NK = log_new_NFV.gather(-1, factors_NFK).sum(-2)
        p_neighbour_NK = (mass_NK + (log_w_new_N.unsqueeze(-1) + log_new_NK).exp()).masked_fill(~offered_NK, -1.0)
        # the readout's mode: its share + the mass of any neighbour holding it
        p_readout_N = (log_w_new_N + best_log_new_NF.sum(-1)).exp() + (
            w_copy_NK * (sources_NK == readout_mode_N.unsqueeze(-1))).sum(-1)
        p_best_neighbour_N, k_N = p_neighbour_NK.max(dim=-1)
        use_neighbour_N = p_best_neighbour_N > p_readout_N
        if self.best_neighbour_copies:  # log weights are -inf where not offered (none offered: no copy is used)
            k_N = log_weights[..., :-1].argmax(dim=-1)
            p_best_neighbour_N = p_neighbour_NK.gather(-1, k_N.unsqueeze(-1)).squeeze(-1)
        ids_N = torch.where(use_neighbour_N, sources_NK.gather(-1, k_N.unsqueeze(-1)).squeeze(-1), readout_mode_N)
        return ids_N, torch.where(use_neighbour_N, p_best_neighbour_N, p_readout_N)


def _mass_per_value(values_NK: torch.Tensor, weights_NK: torch.Tensor):
    """For each entry of each row (..., K): the summed weight of the row's entries with the same value, and whether
    the value already occurred at an earlier index of the row. Works on sorted rows, so nothing of the vocabulary's
    size is allocated."""
    sorted_NK, order_NK = values_NK.sort(dim=-1, stable=True)
    repeat_sorted_NK = F.pad(sorted_NK[..., 1:] == sorted_NK[..., :-1], (1, 0), value=False)
    group_NK = (~repeat_sorted_NK).cumsum(dim=-1) - 1  # runs of equal values, numbered from 0
    totals_NK = torch.zeros_like(weights_NK).scatter_add(-1, group_NK, weights_NK.gather(-1, order_NK))
    mass_NK = torch.empty_like(totals_NK).scatter(-1, order_NK, totals_NK.gather(-1, group_NK))
    return mass_NK, torch.empty_like(repeat_sorted_NK).scatter(-1, order_NK, repeat_sorted_NK)


def previous_frames(x_BTHW: torch.Tensor, mask_token_id: int,
                    before_BHW: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The frame before each frame of x (B, T, H, W): before_BHW (the frame preceding x, None: unknown = all
    mask tokens) for the first, then x's frames 0..T-2."""
    if before_BHW is None:
        before_BHW = torch.full_like(x_BTHW[:, 0], mask_token_id)
    return torch.cat([before_BHW.unsqueeze(1), x_BTHW[:, :-1]], dim=1)
