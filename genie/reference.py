"""Reference computations without the KV cache or the masked readout: the straightforward (published) procedures
that genie/inference.py and the loss of genie/model.py are tested against and benchmarks/bench_eval.py compares with, and
the copy head's mixture written out densely (genie/copy_head.py is tested against it, benchmarks/bench_copy_head.py
compares their speed).

Every MaskGIT step recomputes the whole window through `STMaskGIT.predict_frames` without a cache, frames not yet
known set to the mask token; the loss reads out the logits of every token.
"""
from typing import Optional, Tuple

import torch
import torch.nn.functional as F
from einops import rearrange

from genie.factorization import factorize_token_ids
from genie.metrics import factored_argmax_correct, factored_cross_entropy
from genie.inference import (check_teacher_forced, frame_slice, generation_inputs, sample_targets, stack_frames,
                             targets_to_frames, window_inputs)
from genie.model import LossOutput, MaskGITBatch, action_embeds
from genie.sampling import maskgit_sample


def full_logits_loss(model, batch: MaskGITBatch) -> LossOutput:
    """`STMaskGIT.forward`'s loss (without self-reveal) from the logits of every token."""
    x_BTHW, labels_BTHW = batch.input_ids, batch.labels
    logits_BVFTHW = model.logits(x_BTHW, batch.actions, batch.latent_actions)[:, :, :, 1:]
    relevant_BTHW = x_BTHW[:, 1:] == model.mask_token_id  # frame 0 is always given
    num_relevant = relevant_BTHW.sum().clamp(min=1)
    loss_BTHW = factored_cross_entropy(logits_BVFTHW, labels_BTHW[:, 1:])
    correct_BTHW = factored_argmax_correct(logits_BVFTHW, labels_BTHW[:, 1:])
    return LossOutput(loss=(loss_BTHW * relevant_BTHW).sum() / num_relevant,
                      acc=(correct_BTHW & relevant_BTHW).sum().float() / num_relevant)


@torch.no_grad()
def generate_uncached(model, prompt_BTHW: torch.Tensor, num_new_frames: int, maskgit_steps: int = 2,
                      temperature: float = 0.0, unmask_mode: str = "random",
                      generator: Optional[torch.Generator] = None, actions: Optional[torch.Tensor] = None,
                      latent_actions: Optional[torch.Tensor] = None,
                      control: bool = False) -> Tuple[torch.Tensor, torch.Tensor]:
    """genie.inference.generate_frames by full recomputation: same arguments, same results."""
    cond_BTC, tokens_BTHW = generation_inputs(model, prompt_BTHW, num_new_frames, actions, latent_actions, control)
    T0, total = prompt_BTHW.shape[1], tokens_BTHW.shape[1]
    all_logits = []
    for t in range(T0, total):
        def logits_fn(frame_BHW):
            window_BTHW = tokens_BTHW.clone()
            window_BTHW[:, t] = frame_BHW
            return frame_slice(model.predict_frames(window_BTHW, cond_BTC), t)

        sample_BHW, logits_BVFHW = maskgit_sample(logits_fn, tokens_BTHW[:, t], model.mask_token_id, maskgit_steps,
                                                  temperature, unmask_mode, generator)
        tokens_BTHW[:, t] = sample_BHW
        all_logits.append(logits_BVFHW)
    return tokens_BTHW, torch.stack(all_logits, dim=3)


@torch.no_grad()
def next_frame_recomputed(model, tokens_nHW: torch.Tensor, actions_nD: Optional[torch.Tensor], latent_n: torch.Tensor,
                          maskgit_steps: int, temperature: float,
                          generator: Optional[torch.Generator] = None) -> torch.Tensor:
    """genie.inference.next_frame (a world model environment's step) by recomputing the whole window of n + 1
    frames at every MaskGIT step: same arguments but the cache, the same new frame (H, W)."""
    window_BTHW, cond_BTC = window_inputs(model, tokens_nHW, actions_nD, latent_n)
    n = len(tokens_nHW)

    def logits_fn(frame_BHW):
        current_BTHW = window_BTHW.clone()
        current_BTHW[:, n] = frame_BHW
        return frame_slice(model.predict_frames(current_BTHW, cond_BTC), n)

    frame_BHW, _ = maskgit_sample(logits_fn, window_BTHW[:, n], model.mask_token_id, maskgit_steps, temperature,
                                  "random", generator)
    return frame_BHW[0]


@torch.no_grad()
def teacher_forced_uncached(model, x_BTHW: torch.Tensor, maskgit_steps: int = 2, temperature: float = 0.0,
                            unmask_mode: str = "random", generator: Optional[torch.Generator] = None,
                            actions: Optional[torch.Tensor] = None,
                            latent_actions: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """genie.inference.teacher_forced as the published evaluator computes it: every target and every step
    recomputes the whole window with frames >= t masked; target t knows action rows < t."""
    check_teacher_forced(model, x_BTHW)
    B, T = x_BTHW.shape[:2]

    def logits_fn(frames_NHW):
        frames_BnHW = rearrange(frames_NHW, "(B n) H W -> B n H W", B=B)
        per_target = []
        for t in range(1, T):
            window_BTHW = x_BTHW.clone()
            window_BTHW[:, t] = frames_BnHW[:, t - 1]
            window_BTHW[:, t + 1:] = model.mask_token_id
            cond_BTC = action_embeds(model, B, T, actions, latent_actions, t)
            per_target.append(frame_slice(model.predict_frames(window_BTHW, cond_BTC), t))
        return targets_to_frames(stack_frames(per_target))

    return sample_targets(model, logits_fn, B, T, x_BTHW, maskgit_steps, temperature, unmask_mode, generator)


def dense_copy_mixture(head, logits_NVF: torch.Tensor, hidden_NC: torch.Tensor,
                       sources_NK: torch.Tensor) -> torch.Tensor:
    """genie.copy_head.CopyHead.forward written directly in probability space over every value: a (N, K, F, V)
    one-hot of the neighbours' factors weighted and summed, plus the readout's softmax. Same shapes and result."""
    offered_NK = sources_NK != head.mask_token_id
    scores = head.score_proj(hidden_NC).float().masked_fill(F.pad(~offered_NK, (0, 1)), float("-inf"))
    w_NK1 = scores.softmax(dim=-1)
    factors_NKF = factorize_token_ids(sources_NK.masked_fill(~offered_NK, 0), head.num_factored_vocabs,
                                      head.factored_vocab_size)
    onehot_NKFV = F.one_hot(factors_NKF, head.factored_vocab_size).float()
    copy_NVF = rearrange((w_NK1[..., :-1, None, None] * onehot_NKFV).sum(dim=-3), "... F V -> ... V F")
    return (w_NK1[..., -1, None, None] * logits_NVF.float().softmax(dim=-2) + copy_NVF).log()
