"""Training objectives of the dynamics model: the MaskGIT masked-token loss (with the opt-in self-reveal inputs and
bit loss) and the opt-in two-stream loss. `STMaskGIT.forward` calls `training_loss`.

Both read out only the tokens the loss counts (the (F*V)-wide logits of every other token are most of a small
model's step); genie/reference.py computes the same loss from the logits of every token, and the tests hold the two
equal.
"""
from dataclasses import dataclass
from typing import Optional

import torch
from einops import rearrange

from genie.config import TrainingRecipe
from genie.metrics import factored_argmax_correct, factored_cross_entropy, true_bit_probs
from genie.inference import context_cache
from genie.masking import MaskGITBatch
from genie.sampling import sample_prediction_tokens
from genie.schedule import cosine_schedule
from genie.transformer import TemporalMode


@dataclass
class LossOutput:
    loss: torch.Tensor  # factored CE summed over factors, mean over the predicted tokens
    acc: torch.Tensor  # argmax accuracy (every factor right) over the same tokens


def training_loss(model, batch: MaskGITBatch, recipe: TrainingRecipe) -> LossOutput:
    """The loss of a collated batch: two-stream when it has targets, else the masked-token loss."""
    if batch.target_ids is not None:
        return two_stream_loss(model, batch)
    return masked_loss(model, batch, recipe.self_reveal_ratio, recipe.own_context_ratio, recipe.guess_temperature,
                       recipe.bit_loss_weight)


def masked_loss(model, batch: MaskGITBatch, self_reveal_ratio: float = 0.0, own_context_ratio: float = 0.0,
                guess_temperature: float = 0.0, bit_loss_weight: float = 0.0) -> LossOutput:
    """Factored CE and accuracy over the masked tokens of frames 1..T-1 of batch.input_ids (B, T, H, W).

    In training mode a share own_context_ratio of the examples first predicts its fully masked frames and is then
    trained on the frames after them (`shift_targets_past_own_frames`), a share self_reveal_ratio has part of
    its masked tokens filled with the model's own guesses (`reveal_own_predictions`), and the loss adds
    bit_loss_weight times `bit_loss` of the same tokens.
    """
    x_BTHW, labels_BTHW = batch.input_ids, batch.labels
    model.check_tokens(x_BTHW)
    B, T = x_BTHW.shape[:2]
    cond_BTC = model.with_context_noise(model.action_embeds(B, T, batch.actions, batch.latent_actions),
                                        batch.context_noise)
    if model.training and own_context_ratio > 0:
        x_BTHW = shift_targets_past_own_frames(model, x_BTHW, cond_BTC, own_context_ratio, guess_temperature)
    if model.training and self_reveal_ratio > 0:
        x_BTHW = reveal_own_predictions(model, x_BTHW, cond_BTC, self_reveal_ratio, guess_temperature)
    sources_BTSK = model.window_copy_sources(x_BTHW)
    x_BTSC = model.hidden_states(x_BTHW, cond_BTC, sources_BTSK=sources_BTSK)
    relevant_BTS = rearrange(x_BTHW == model.mask_token_id, "B T H W -> B T (H W)")
    relevant_BTS[:, 0] = False  # frame 0 is always given
    return loss_at(model, x_BTSC, relevant_BTS, rearrange(labels_BTHW, "B T H W -> B T (H W)"), sources_BTSK,
                   bit_loss_weight if model.training else 0.0)


@torch.no_grad()
def own_guesses(model, x_bTHW: torch.Tensor, cond_bTC: Optional[torch.Tensor],
                where_bTHW: torch.Tensor, temperature: float = 0.0) -> torch.Tensor:
    """The model's one-pass predictions (N,) of the positions `where_bTHW` (b, T, H, W) of x_bTHW: each factor's
    argmax at temperature 0; above it tokens drawn as a sampled rollout draws them (`sample_prediction_tokens`),
    from torch's global random numbers."""
    where_bTS = rearrange(where_bTHW, "b T H W -> b T (H W)")
    sources_bTSK = model.window_copy_sources(x_bTHW)
    hidden_NC = model.hidden_states(x_bTHW, cond_bTC, sources_BTSK=sources_bTSK)[where_bTS]
    sources_NK = None if sources_bTSK is None else sources_bTSK[where_bTS]
    # at temperature 0 each factor's argmax: for a copy head, not the joint mode that inference decodes with
    # (`CopyHead.mode`); the trained recipe's guesses are kept as they were
    prediction = model.predict(hidden_NC, sources_NK, with_mode=temperature > 0, greedy=False)
    prediction_1S = prediction.map(lambda v: rearrange(v, "N V F -> 1 V F N"), lambda v: v.unsqueeze(0))
    return sample_prediction_tokens(prediction_1S, temperature)[0][0]


@torch.no_grad()
def shift_targets_past_own_frames(model, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor],
                                  ratio: float, temperature: float = 0.0) -> torch.Tensor:
    """Training inputs (B, T, H, W) whose targets follow the model's own frames, for a share `ratio` of the
    examples: each fully masked frame t >= 1 is filled with the model's one-pass prediction (`own_guesses` at
    `temperature`; one extra pass without gradients) and frame t+1, when it exists and is not fully masked itself,
    is masked whole instead.

    In a free-running rollout every generated frame after the first is predicted from a context whose last frames
    are the model's own guesses (on the sample world mostly wrong tokens, and what the copy head copies from); a
    model trained only on true context frames has never seen one.
    """
    whole_BT = (x_BTHW == model.mask_token_id).flatten(2).all(-1)
    whole_BT[:, 0] = False
    chosen_B = (torch.rand(x_BTHW.shape[0], device=x_BTHW.device) < ratio) & whole_BT.any(1)
    if not chosen_B.any():
        return x_BTHW
    x_bTHW, whole_bT = x_BTHW[chosen_B], whole_BT[chosen_B]  # a copy
    fill_bTHW = whole_bT[:, :, None, None].expand_as(x_bTHW)
    guesses_N = own_guesses(model, x_bTHW, None if cond_BTC is None else cond_BTC[chosen_B], fill_bTHW, temperature)
    next_bT = torch.zeros_like(whole_bT)
    next_bT[:, 1:] = whole_bT[:, :-1] & ~whole_bT[:, 1:]
    x_bTHW[fill_bTHW] = guesses_N
    x_bTHW[next_bT] = model.mask_token_id
    return x_BTHW.index_put((chosen_B,), x_bTHW)


@torch.no_grad()
def reveal_own_predictions(model, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor],
                           ratio: float, temperature: float = 0.0) -> torch.Tensor:
    """Training inputs (B, T, H, W) as a later MaskGIT step sees them: for a share `ratio` of the examples, a
    random share 1 - cos(pi/2 u), u ~ U(0, 1), of each frame's masked tokens is filled with the model's own
    prediction (`own_guesses` at `temperature`; one extra pass without gradients).

    At inference the tokens revealed after step 1 are the model's guesses (on the sample world ~11 % of them
    right), not the ground truth that published masking reveals; a model trained only on ground truth trusts
    them, and its second step gets worse than its first. Sampled rollouts reveal drawn tokens instead of the
    argmax, which a temperature > 0 shows the model.
    """
    chosen_B = torch.rand(x_BTHW.shape[0], device=x_BTHW.device) < ratio
    if not chosen_B.any():
        return x_BTHW
    x_bTHW = x_BTHW[chosen_B]  # a copy
    masked_bTHW = x_bTHW == model.mask_token_id
    masked_bTHW[:, 0] = False
    guesses_N = own_guesses(model, x_bTHW, None if cond_BTC is None else cond_BTC[chosen_B], masked_bTHW,
                            temperature)
    share_bT11 = 1 - cosine_schedule(torch.rand(*masked_bTHW.shape[:2], 1, 1, device=x_BTHW.device))
    reveal_bTHW = masked_bTHW & (torch.rand(masked_bTHW.shape, device=x_BTHW.device) < share_bT11)
    x_bTHW[masked_bTHW] = torch.where(reveal_bTHW[masked_bTHW], guesses_N, model.mask_token_id)
    return x_BTHW.index_put((chosen_B,), x_bTHW)


def two_stream_loss(model, batch: MaskGITBatch) -> LossOutput:
    """Loss and acc of the masked tokens of targets 1..T-1 (batch.target_ids), each over the clean context frames
    < t (batch.input_ids), all (B, T, H, W).

    The computation of the cached teacher-forced evaluation (context keys/values once, then all targets in one
    pass), here with gradients: the cache's buffers are written in place, which autograd records like any slice
    copy.
    """
    context_BTHW, targets_BTHW = batch.input_ids, batch.target_ids
    model.check_tokens(context_BTHW)
    model.check_tokens(targets_BTHW)
    if targets_BTHW.shape != context_BTHW.shape:
        raise ValueError(f"target_ids must have the shape of input_ids {tuple(context_BTHW.shape)}, got "
                         f"{tuple(targets_BTHW.shape)}")
    if (context_BTHW == model.mask_token_id).any():
        raise ValueError("two-stream training: the context frames (input_ids) must not hold mask tokens")
    B, T = context_BTHW.shape[:2]
    cond_BTC = model.action_embeds(B, T, batch.actions, batch.latent_actions)
    kv_cache = context_cache(model, context_BTHW, cond_BTC)
    sources_BTSK = model.copy_sources(context_BTHW[:, :-1])
    x_BTSC = model.hidden_states(targets_BTHW[:, 1:], None if cond_BTC is None else cond_BTC[:, 1:], 1,
                                 TemporalMode.TARGETS, kv_cache, sources_BTSK)
    relevant_BTS = rearrange(targets_BTHW[:, 1:] == model.mask_token_id, "B T H W -> B T (H W)")
    return loss_at(model, x_BTSC, relevant_BTS, rearrange(batch.labels[:, 1:], "B T H W -> B T (H W)"),
                   sources_BTSK)


def loss_at(model, x_BTSC: torch.Tensor, relevant_BTS: torch.Tensor, labels_BTS: torch.Tensor,
            sources_BTSK: Optional[torch.Tensor] = None, bit_loss_weight: float = 0.0) -> LossOutput:
    """Read out the hidden states (B, T, S, C) where relevant (B, T, S) only -> factored CE and acc there, plus
    bit_loss_weight times their `bit_loss` in the loss. sources_BTSK: the copy head's sources of every position
    (`STMaskGIT.copy_sources`), None without one."""
    factored_NVF = model.readout(x_BTSC[relevant_BTS], None if sources_BTSK is None else sources_BTSK[relevant_BTS])
    targets_N = labels_BTS[relevant_BTS]
    num_relevant = max(targets_N.numel(), 1)
    loss = factored_cross_entropy(factored_NVF, targets_N).sum() / num_relevant
    if bit_loss_weight > 0:
        loss = loss + bit_loss_weight * bit_loss(factored_NVF, targets_N).sum() / num_relevant
    acc = factored_argmax_correct(factored_NVF, targets_N).sum().float() / num_relevant
    return LossOutput(loss=loss, acc=acc)


def bit_loss(factored_NVF: torch.Tensor, targets_N: torch.Tensor) -> torch.Tensor:
    """Per-token binary cross entropy of the id's bits (N,): -log `true_bit_probs`, summed over the F * J bits.

    A token drawn from the prediction has on average sum(1 - true_bit_probs) wrong bits, and each wrong bit costs
    far less in decoded pixels than a wrong token does (on the sample world's tokenizer, one flipped bit on a
    quarter of the positions leaves a frame at ~40 dB, a random token at ~27), which CE's all-or-nothing target
    does not see.
    """
    return -true_bit_probs(factored_NVF, targets_N).clamp_min(1e-30).log().sum(dim=(1, 2))
