"""MaskGIT decoding of one frame of tokens with factored logits (docs/formats.md §5), batched over frames, and the
mask schedule it shares with the training collator.

Differences from the published sampler, on purpose: the temperature divides the logits (the published code
divides the probabilities, which Categorical renormalizes, so its temperature had no effect), and tokens given in
the input frame are never changed.
"""
import math
from typing import Callable, Optional, Tuple, Union

import torch
from einops import rearrange

from genie.copy_head import Prediction
from genie.decoding import UNMASK_MODES
from genie.factorization import factorize_token_ids, unfactorize_token_ids

GREEDY_TEMPERATURE = 1e-8  # at or below this temperature, sampling is argmax


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


def sample_factored_tokens(logits_BVFS: torch.Tensor, temperature: float = 0.0,
                           generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sample each factor independently; return (token ids (B, S), confidence (B, S)).

    logits_BVFS: (B, V, F, S) factored logits, factor 0 the least significant (token = sum_k f_k V^k).
    temperature <= 1e-8 (as in the published code) takes the argmax; otherwise factors are drawn from
    softmax(logits / temperature).
    The confidence is the product over factors of each drawn factor's probability under softmax(logits).
    """
    if temperature < 0:
        raise ValueError(f"temperature must be >= 0, got {temperature}")
    logits_BSFV = rearrange(logits_BVFS.float(), "B V F S -> B S F V")
    B, S, F_, V = logits_BSFV.shape
    if temperature <= GREEDY_TEMPERATURE:
        factors_BSF = logits_BSFV.argmax(dim=-1)
    else:
        tempered = (logits_BSFV / temperature).softmax(dim=-1).reshape(-1, V)
        factors_BSF = torch.multinomial(tempered, 1, generator=generator).view(B, S, F_)
    # softmax probability of the drawn factors, without materializing the whole softmax
    log_probs_BSF = logits_BSFV.gather(-1, factors_BSF.unsqueeze(-1)).squeeze(-1) - logits_BSFV.logsumexp(dim=-1)
    confidence_BS = log_probs_BSF.sum(dim=-1).exp()
    return unfactorize_token_ids(factors_BSF, F_, V), confidence_BS


def sample_mixture_tokens(log_weights_NK1: torch.Tensor, sources_NK: torch.Tensor, readout_NVF: torch.Tensor,
                          temperature: float = 1.0,
                          generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Draw whole tokens from a copy head's mixture; return (token ids (...), their mixture probabilities (...)).

    log_weights_NK1 (..., K + 1): log weights of the K neighbours and, last, of a new token (-inf: not offered);
    sources_NK (..., K): the neighbours' token ids; readout_NVF (..., V, F): the readout's factored logits.
    Each position first draws an option from softmax(log weights / temperature), then, for the new-token option,
    each factor from softmax(readout / temperature). At temperature 1 that is an exact draw from the mixture over
    whole tokens; drawing each factor from the mixture's marginals instead (`sample_factored_tokens`) can pair one
    neighbour's low factor with another's high factor, a token no option proposed. Other temperatures temper the
    option and the readout separately (the mixture's own tempered distribution has no such closed form).
    """
    if temperature <= GREEDY_TEMPERATURE:
        raise ValueError(f"sample_mixture_tokens draws at a temperature > {GREEDY_TEMPERATURE}, got {temperature}")
    K = sources_NK.shape[-1]
    V, F_ = readout_NVF.shape[-2:]
    shape = sources_NK.shape[:-1]
    log_w_MK1 = log_weights_NK1.reshape(-1, K + 1).float()
    option_M = torch.multinomial((log_w_MK1 / temperature).softmax(dim=-1), 1, generator=generator).squeeze(-1)
    readout_MFV = rearrange(readout_NVF.reshape(-1, V, F_).float(), "M V F -> M F V")
    new_MF = torch.multinomial((readout_MFV / temperature).softmax(dim=-1).reshape(-1, V), 1,
                               generator=generator).view(-1, F_)
    sources_MK = sources_NK.reshape(-1, K)
    copied_M = sources_MK.gather(-1, option_M.clamp(max=K - 1).unsqueeze(-1)).squeeze(-1)
    ids_M = torch.where(option_M == K, unfactorize_token_ids(new_MF, F_, V), copied_M)
    # the drawn token's probability under the (untempered) mixture: the copy mass of the neighbours holding it
    # plus the new-token weight times the readout's probability of its factors
    w_MK1 = log_w_MK1.exp()
    ids_factors_MF = factorize_token_ids(ids_M, F_, V)
    log_readout_M = (readout_MFV.log_softmax(dim=-1).gather(-1, ids_factors_MF.unsqueeze(-1))).sum(dim=(-2, -1))
    probs_M = (w_MK1[:, :K] * (sources_MK == ids_M.unsqueeze(-1))).sum(-1) + w_MK1[:, K] * log_readout_M.exp()
    return ids_M.view(shape), probs_M.view(shape)


def sample_prediction_tokens(prediction_BS: Prediction, temperature: float,
                             generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Tokens drawn from a prediction at S positions of B rows: (ids (B, S), confidence (B, S)).

    prediction_BS: logits and readout_logits (B, V, F, S), the copy parts (B, S, K + 1) and (B, S, K). At a
    temperature a copy head's mixture draws whole tokens (`sample_mixture_tokens`) and any other prediction each
    factor (`sample_factored_tokens`, which at temperature <= GREEDY_TEMPERATURE takes each factor's argmax).
    """
    if prediction_BS.copy_log_weights is not None and temperature > GREEDY_TEMPERATURE:
        return sample_mixture_tokens(prediction_BS.copy_log_weights, prediction_BS.copy_sources,
                                     rearrange(prediction_BS.readout_logits, "B V F S -> B S V F"), temperature,
                                     generator)
    return sample_factored_tokens(prediction_BS.logits, temperature, generator)


def maskgit_sample(logits_fn: Callable[[torch.Tensor], Union[torch.Tensor, Prediction]], frame_BHW: torch.Tensor,
                   mask_token_id: int, maskgit_steps: int, temperature: float = 0.0, unmask_mode: str = "random",
                   generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Fill the masked tokens of a batch of frames in `maskgit_steps` steps.

    logits_fn: (B, H, W) token ids (mask_token_id where unknown) -> factored logits (B, V, F, H, W), or a
    `Prediction` of them with mode ids and probabilities (B, H, W), which greedy steps then take (and their
    probabilities as confidences) instead of the factor-wise argmax, and / or with a copy head's mixture parts,
    from which steps at a temperature then draw whole tokens (`sample_mixture_tokens`).
    frame_BHW: the starting frames; tokens other than mask_token_id are given and are never changed.
    After step s (of n), ceil(cos(pi/2 (s+1)/n) * S) tokens stay masked (`num_masked_after_step`); the last step reveals
    all. Which masked tokens are revealed: "random" (the published default) or "greedy" (most confident first).
    Random numbers are drawn in a fixed order (token samples, then the reveal order, each step), so two callers
    whose logits_fn agree draw the same samples from the same generator.

    Returns (samples (B, H, W) with no mask token left, factored logits of the first step (B, V, F, H, W)).
    """
    if maskgit_steps < 1:
        raise ValueError(f"maskgit_steps must be >= 1, got {maskgit_steps}")
    if unmask_mode not in UNMASK_MODES:
        raise ValueError(f"unmask_mode must be one of {UNMASK_MODES}, got {unmask_mode!r}")
    B, H, W = frame_BHW.shape
    S = H * W
    frame_BS = frame_BHW.reshape(B, S).clone()
    first_logits = None
    for step in range(maskgit_steps):
        prediction = logits_fn(frame_BS.view(B, H, W))
        if not isinstance(prediction, Prediction):
            prediction = Prediction(prediction)
        logits_BVFHW = prediction.logits
        if first_logits is None:
            first_logits = logits_BVFHW
        if prediction.mode_ids is not None and temperature <= GREEDY_TEMPERATURE:
            tokens_BS, confidence_BS = prediction.mode_ids.reshape(B, S), prediction.mode_probs.reshape(B, S)
        else:
            tokens_BS, confidence_BS = sample_prediction_tokens(prediction.map(
                lambda v: v.flatten(3), lambda v: v.reshape(B, S, *v.shape[3:])), temperature, generator)
        masked_BS = frame_BS == mask_token_id
        reveal_BS = masked_BS
        num_left = num_masked_after_step(step, maskgit_steps, S)
        if num_left > 0:
            if unmask_mode == "random":
                scores_BS = torch.rand(B, S, generator=generator, device=frame_BS.device)
            else:
                scores_BS = confidence_BS
            # the lowest-scoring masked tokens stay masked; known tokens score +inf so they are never picked
            scores_BS = scores_BS.masked_fill(~masked_BS, float("inf"))
            stay_BS = torch.zeros_like(masked_BS).scatter_(1, scores_BS.topk(num_left, dim=1, largest=False).indices,
                                                           True)
            reveal_BS = masked_BS & ~stay_BS
        frame_BS = torch.where(reveal_BS, tokens_BS, frame_BS)
    return frame_BS.view(B, H, W), first_logits
