"""MaskGIT decoding of one frame of tokens with factored logits (docs/formats.md §5), batched over frames.

Differences from the published sampler, on purpose: the temperature divides the logits (the published code
divides the probabilities, which Categorical renormalizes, so its temperature had no effect), and tokens given in
the input frame are never changed.
"""
from typing import Callable, NamedTuple, Optional, Tuple, Union

import torch
from einops import rearrange

from genie.factorization import unfactorize_token_ids
from genie.schedule import num_masked_after_step

UNMASK_MODES = ("random", "greedy")
GREEDY_TEMPERATURE = 1e-8  # at or below this temperature, sampling is argmax


class Prediction(NamedTuple):
    """A model's prediction at some positions: factored logits (..., V, F) (log-probabilities for a model with a
    copy head) and, when its greedy choice is not the factor-wise argmax of those (the copy head's mixture,
    `CopyHead.mode`), the most probable whole token ids (...) and their probabilities (...)."""
    logits: torch.Tensor
    mode_ids: Optional[torch.Tensor] = None
    mode_probs: Optional[torch.Tensor] = None


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


def maskgit_sample(logits_fn: Callable[[torch.Tensor], Union[torch.Tensor, Prediction]], frame_BHW: torch.Tensor,
                   mask_token_id: int, maskgit_steps: int, temperature: float = 0.0, unmask_mode: str = "random",
                   generator: Optional[torch.Generator] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Fill the masked tokens of a batch of frames in `maskgit_steps` steps.

    logits_fn: (B, H, W) token ids (mask_token_id where unknown) -> factored logits (B, V, F, H, W), or a
    `Prediction` of them with mode ids and probabilities (B, H, W), which greedy steps then take (and their
    probabilities as confidences) instead of the factor-wise argmax.
    frame_BHW: the starting frames; tokens other than mask_token_id are given and are never changed.
    After step s (of n), ceil(cos(pi/2 (s+1)/n) * S) tokens stay masked (genie.schedule); the last step reveals
    all. Which masked tokens are revealed: "random" (the published default) or "greedy" (most confident first).
    Random numbers are drawn in a fixed order (factor samples, then the reveal order, each step), so two callers
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
            tokens_BS, confidence_BS = sample_factored_tokens(logits_BVFHW.flatten(3), temperature, generator)
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
