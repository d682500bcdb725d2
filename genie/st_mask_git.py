"""STMaskGIT: the GENIE dynamics model, loadable from the published GENIE_35M / GENIE_138M checkpoints.

Token ids (B, T, H, W) -> factored logits. Parameter names, shapes and math follow FORMATS.md 3 exactly.
Inference entry points:
- `generate`: autoregressive frames after a prompt, MaskGIT within each frame, temporal KV cache across frames.
- `teacher_forced`: the challenge protocol (FORMATS.md 5): every frame t = 1..T-1 predicted from ground truth
  frames < t; the ground-truth context is computed once, all targets together in one pass per MaskGIT step.
Both take `use_cache=False` for the straightforward full recomputation (the reference they are tested against).
With opt-in action inputs (config.action_names / num_latent_actions, genie/actions.py) every entry point takes
per-frame `actions` (B, T, D) and `latent_actions` (B, T) and applies the same known-rows rule in both paths.
"""
import math
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Tuple, Union

import safetensors.torch
import torch
from einops import rearrange
from huggingface_hub import PyTorchModelHubMixin, hf_hub_download
from torch import nn

from common.errors import CheckpointError
from common.integrity import update_manifest, verify_manifest
from genie.actions import ActionConditioning
from genie.config import GenieConfig, load_json
from genie.evaluation import factored_argmax_correct, factored_cross_entropy
from genie.factorization import factorize_token_ids
from genie.sampling import maskgit_sample, sample_factored_tokens
from genie.schedule import cosine_schedule
from genie.st_transformer import STTransformerDecoder, TemporalKVCache

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"
MUP_BASE_D_MODEL = 256  # the published muP base shape (set_mup_shapes hard-codes d_model 256)




class FactorizedEmbedding(nn.Module):
    """A token's embedding is the sum of its factors' embeddings; the mask token has its own embedding."""

    def __init__(self, factored_vocab_size: int, num_factored_vocabs: int, d_model: int, mask_token_id: int):
        super().__init__()
        self.factored_vocab_size = factored_vocab_size
        self.num_factored_vocabs = num_factored_vocabs
        self.mask_token_id = mask_token_id
        self.factored_embeds = nn.ModuleList([nn.Embedding(factored_vocab_size, d_model)
                                              for _ in range(num_factored_vocabs)])
        self.mask_token_embed = nn.Parameter(torch.zeros(1, d_model))

    def forward(self, token_ids: torch.Tensor) -> torch.Tensor:
        """(...) token ids in [0, image_vocab_size] (the last is the mask token) -> (..., d_model)."""
        is_mask = token_ids == self.mask_token_id
        factors = factorize_token_ids(token_ids.masked_fill(is_mask, 0), self.num_factored_vocabs,
                                      self.factored_vocab_size).unbind(-1)
        embeds = self.factored_embeds[0](factors[0])
        for embed, factor in zip(self.factored_embeds[1:], factors[1:]):
            embeds = embeds + embed(factor)
        return torch.where(is_mask.unsqueeze(-1), self.mask_token_embed.to(embeds.dtype), embeds)


@dataclass
class STMaskGITOutput:
    loss: torch.Tensor  # factored CE summed over factors, mean over the masked tokens of frames 1..T-1
    acc: torch.Tensor  # argmax accuracy (all factors right) over the same tokens
    logits: Optional[torch.Tensor]  # (B, F*V, T, H, W), channel f*V + v is factor f, value v; None
    # when forward was called with return_logits=False


class STMaskGIT(nn.Module, PyTorchModelHubMixin):
    def __init__(self, config: GenieConfig):
        super().__init__()
        self.config = config
        self.h = self.w = config.H
        self.mask_token_id = config.mask_token_id
        self.decoder = STTransformerDecoder(config)
        self.pos_embed_TSC = nn.Parameter(torch.zeros(1, config.T, config.S, config.d_model))
        self.token_embed = FactorizedEmbedding(config.factored_vocab_size, config.num_factored_vocabs,
                                               config.d_model, config.mask_token_id)
        self.out_x_proj = nn.Linear(config.d_model, config.factored_vocab_size * config.num_factored_vocabs)
        # muP readout (mup.MuReadout with output_mult 1): the input is divided by d_model / base d_model
        self.readout_width_mult = config.d_model / MUP_BASE_D_MODEL if config.use_mup else None
        # only when enabled, so the published parameter layout is unchanged
        self.action_cond = ActionConditioning(config) if config.uses_actions else None

    def init_weights(self) -> None:
        """Normal(0, 0.02) for Linear and Embedding weights, zero biases (as published); sin-cos positions.

        The published code leaves pos_embed_TSC at zero, so at first temporal attention cannot tell the previous
        frame from any earlier one and must learn positions from scratch before it can learn to copy; a sin-cos
        start (of the same scale as the token embeddings) makes a small model learn that in a few hundred steps.
        Loading a checkpoint replaces it, so published weights behave exactly as published.
        """
        for module in self.modules():
            if isinstance(module, (nn.Linear, nn.Embedding)):
                nn.init.normal_(module.weight, mean=0.0, std=0.02)
            if isinstance(module, nn.Linear) and module.bias is not None:
                nn.init.zeros_(module.bias)
        with torch.no_grad():
            self.pos_embed_TSC.copy_(sincos_pos_embed(self.config.T, self.config.S, self.config.d_model))

    # ---------------------------------------------------------------- core computation
    def _check_tokens(self, x_BTHW: torch.Tensor, first_frame: int = 0) -> None:
        if x_BTHW.dim() != 4 or x_BTHW.shape[2] * x_BTHW.shape[3] != self.config.S:
            raise ValueError(f"expected token ids of shape (B, T, H, W) with H*W = S = {self.config.S}, "
                             f"got {tuple(x_BTHW.shape)}")
        if first_frame + x_BTHW.shape[1] > self.config.T:
            raise ValueError(f"frames {first_frame}..{first_frame + x_BTHW.shape[1] - 1} requested, but the model "
                             f"has position embeddings for T = {self.config.T} frames only")
        if x_BTHW.is_floating_point():
            raise ValueError(f"token ids must be integers, got {x_BTHW.dtype}")
        if ((x_BTHW < 0) | (x_BTHW > self.mask_token_id)).any():
            raise ValueError(f"token ids must be in [0, {self.config.image_vocab_size}) or the mask token "
                             f"{self.mask_token_id}; got values in [{x_BTHW.min().item()}, {x_BTHW.max().item()}]")

    def _embed(self, x_BTS: torch.Tensor, first_frame: int, cond_BTC: Optional[torch.Tensor] = None) -> torch.Tensor:
        """Token ids of frames first_frame.. (B, T, S) -> input embeddings (B, T, S, C).

        cond_BTC: action embeddings of these frames (B, T, C), added to every token of a frame.
        """
        T = x_BTS.shape[1]
        x_BTSC = self.token_embed(x_BTS) + self.pos_embed_TSC[:, first_frame:first_frame + T]
        return x_BTSC if cond_BTC is None else x_BTSC + cond_BTC.unsqueeze(2).to(x_BTSC.dtype)

    def action_embeds(self, B: int, T: int, actions: Optional[torch.Tensor] = None,
                      latent_actions: Optional[torch.Tensor] = None,
                      known_T: Union[int, torch.Tensor, None] = None) -> Optional[torch.Tensor]:
        """Action embeddings (B, T, C) of window frames 0..T-1, or None for a model without action inputs.

        actions (B, T, D) float, latent_actions (B, T) ids: per-frame rows as in the dataset (genie/actions.py).
        known_T: how many leading rows each frame may use (int or (T,)); None: all of them.
        A model without action inputs raises when given actions.
        """
        if self.action_cond is None:
            if actions is not None or latent_actions is not None:
                raise ValueError("this model has no action inputs (its config sets neither action_names nor "
                                 "num_latent_actions); do not pass actions or latent_actions")
            return None
        self.action_cond.check_inputs(actions, latent_actions, B, T)
        device = self.pos_embed_TSC.device
        return self.action_cond(B, T, actions, latent_actions, T if known_T is None else known_T, device)

    def _readout(self, x_BTSC: torch.Tensor) -> torch.Tensor:
        if self.readout_width_mult is not None:
            x_BTSC = x_BTSC / self.readout_width_mult
        return self.out_x_proj(x_BTSC)

    def _factored(self, logits_BTSC: torch.Tensor) -> torch.Tensor:
        """(B, T, S, F*V) -> factored (B, V, F, T, H, W)."""
        return rearrange(logits_BTSC, "B T (H W) (F V) -> B V F T H W", H=self.h, F=self.config.num_factored_vocabs)

    def compute_logits(self, x_BTHW: torch.Tensor, actions: Optional[torch.Tensor] = None,
                       latent_actions: Optional[torch.Tensor] = None,
                       known_T: Union[int, torch.Tensor, None] = None) -> torch.Tensor:
        """Token ids of frames 0..T-1 (B, T, H, W), T <= config.T -> logits (B, F*V, T, H, W).

        actions / latent_actions / known_T: per-frame action inputs, see `action_embeds`.
        """
        self._check_tokens(x_BTHW)
        B, T = x_BTHW.shape[:2]
        return self._full_logits(x_BTHW, self.action_embeds(B, T, actions, latent_actions, known_T))

    def _full_logits(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor] = None) -> torch.Tensor:
        """compute_logits without input checks, with precomputed action embeddings (B, T, C) or None."""
        return rearrange(self._readout(self._decode(x_BTHW, cond_BTC)), "B T (H W) C -> B C T H W", H=self.h)

    def _decode(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor]) -> torch.Tensor:
        """Frames 0..T-1 (B, T, H, W) through the decoder -> final hidden states (B, T, S, C), before the readout."""
        return self.decoder(self._embed(rearrange(x_BTHW, "B T H W -> B T (H W)"), 0, cond_BTC))

    def forward(self, input_ids: torch.Tensor, labels: torch.Tensor, actions: Optional[torch.Tensor] = None,
                latent_actions: Optional[torch.Tensor] = None, return_logits: bool = True,
                target_ids: Optional[torch.Tensor] = None, **kwargs) -> STMaskGITOutput:
        """input_ids, labels: (B, T*H*W) flattened token ids; input_ids hold the mask token where corrupted.

        actions (B, T, D), latent_actions (B, T): the model's action inputs (all rows known, as in training), used
        when the config enables them; a video-only model ignores them, like the other batch entries
        (attention_mask, ...).
        return_logits=False (training): read out only the masked tokens the loss counts, skipping the (F*V)-wide
        logits of every other token (most of a small model's step), and return logits=None; loss and acc are the
        same. In training mode this path also applies config.self_reveal_ratio (`_reveal_own_predictions`).
        target_ids (B, T*H*W): the two-stream teacher-forced objective (genie.masking.get_maskgit_collator with
        two_stream_ratio): input_ids are then whole context frames (no mask tokens) and frame t >= 1 of target_ids,
        masked where it is to be predicted, is a target that sees context frames < t and itself only, as in
        `teacher_forced`; every frame of a window is a target, each with its full history. logits=None.
        """
        S = self.config.S
        if input_ids.dim() != 2 or input_ids.shape[1] % S or input_ids.shape != labels.shape:
            raise ValueError(f"input_ids and labels must both be (B, T*{S}); got {tuple(input_ids.shape)} and "
                             f"{tuple(labels.shape)}")
        x_BTHW = rearrange(input_ids, "B (T H W) -> B T H W", H=self.h, W=self.w)
        labels_BTHW = rearrange(labels, "B (T H W) -> B T H W", H=self.h, W=self.w)
        if self.action_cond is None:
            actions = latent_actions = None
        if target_ids is not None:
            if target_ids.shape != input_ids.shape:
                raise ValueError(f"target_ids must have the shape of input_ids {tuple(input_ids.shape)}, got "
                                 f"{tuple(target_ids.shape)}")
            targets_BTHW = rearrange(target_ids, "B (T H W) -> B T H W", H=self.h, W=self.w)
            return self._two_stream_loss(x_BTHW, targets_BTHW, labels_BTHW, actions, latent_actions)
        if not return_logits:
            return self._masked_loss(x_BTHW, labels_BTHW, actions, latent_actions)
        logits_BCTHW = self.compute_logits(x_BTHW, actions, latent_actions)

        # frame 0 is always given; only the masked tokens of frames 1.. count
        factored_BVFTHW = rearrange(logits_BCTHW[:, :, 1:], "B (F V) T H W -> B V F T H W",
                                    F=self.config.num_factored_vocabs)
        relevant_BTHW = x_BTHW[:, 1:] == self.mask_token_id
        num_relevant = relevant_BTHW.sum().clamp(min=1)
        loss_BTHW = factored_cross_entropy(factored_BVFTHW, labels_BTHW[:, 1:])
        correct_BTHW = factored_argmax_correct(factored_BVFTHW, labels_BTHW[:, 1:])
        loss = (loss_BTHW * relevant_BTHW).sum() / num_relevant
        acc = (correct_BTHW & relevant_BTHW).sum().float() / num_relevant
        return STMaskGITOutput(loss=loss, acc=acc, logits=logits_BCTHW)

    def _masked_loss(self, x_BTHW: torch.Tensor, labels_BTHW: torch.Tensor, actions: Optional[torch.Tensor],
                     latent_actions: Optional[torch.Tensor]) -> STMaskGITOutput:
        """forward's loss and acc with the readout applied only to the masked tokens of frames 1.. (logits=None)."""
        self._check_tokens(x_BTHW)
        B, T = x_BTHW.shape[:2]
        cond_BTC = self.action_embeds(B, T, actions, latent_actions)
        if self.training and self.config.self_reveal_ratio > 0:
            x_BTHW = self._reveal_own_predictions(x_BTHW, cond_BTC)
        x_BTSC = self._decode(x_BTHW, cond_BTC)
        relevant_BTS = rearrange(x_BTHW == self.mask_token_id, "B T H W -> B T (H W)")
        relevant_BTS[:, 0] = False
        return self._loss_at(x_BTSC, relevant_BTS, rearrange(labels_BTHW, "B T H W -> B T (H W)"))

    @torch.no_grad()
    def _reveal_own_predictions(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor]) -> torch.Tensor:
        """Training inputs (B, T, H, W) as a later MaskGIT step sees them: for config.self_reveal_ratio of the
        examples, a random share 1 - cos(pi/2 u), u ~ U(0, 1), of each frame's masked tokens is filled with the
        model's own greedy prediction (one extra pass without gradients).

        At inference the tokens revealed after step 1 are the model's guesses (on the sample world ~11 % of them
        right), not the ground truth that published masking reveals; a model trained only on ground truth trusts
        them, and its second step gets worse than its first.
        """
        chosen_B = torch.rand(x_BTHW.shape[0], device=x_BTHW.device) < self.config.self_reveal_ratio
        if not chosen_B.any():
            return x_BTHW
        x_bTHW = x_BTHW[chosen_B]  # a copy
        masked_bTHW = x_bTHW == self.mask_token_id
        masked_bTHW[:, 0] = False
        hidden_NC = self._decode(x_bTHW, None if cond_BTC is None else cond_BTC[chosen_B])[
            rearrange(masked_bTHW, "b T H W -> b T (H W)")]
        logits_1VFN = rearrange(self._readout(hidden_NC), "N (F V) -> 1 V F N", F=self.config.num_factored_vocabs)
        guesses_N = sample_factored_tokens(logits_1VFN, temperature=0.0)[0][0]  # greedy, as the sampler picks
        share_bT11 = 1 - cosine_schedule(torch.rand(*masked_bTHW.shape[:2], 1, 1, device=x_BTHW.device))
        reveal_bTHW = masked_bTHW & (torch.rand(masked_bTHW.shape, device=x_BTHW.device) < share_bT11)
        x_bTHW[masked_bTHW] = torch.where(reveal_bTHW[masked_bTHW], guesses_N, self.mask_token_id)
        return x_BTHW.index_put((chosen_B,), x_bTHW)

    def _context_cache(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor]) -> TemporalKVCache:
        """Temporal keys/values of context frames 0..T-2 of a window (B, T, H, W), for targets 1..T-1."""
        n = x_BTHW.shape[1] - 1
        kv_cache = self.new_kv_cache(n)
        self._run_frames(x_BTHW[:, :n], 0, kv_cache, commit=n, readout=False, cond_BTC=_frames(cond_BTC, 0, n))
        return kv_cache

    def _two_stream_loss(self, context_BTHW: torch.Tensor, targets_BTHW: torch.Tensor, labels_BTHW: torch.Tensor,
                         actions: Optional[torch.Tensor], latent_actions: Optional[torch.Tensor]) -> STMaskGITOutput:
        """Loss and acc of the masked tokens of targets 1..T-1, each over context frames < t (all (B, T, H, W)).

        The same computation as `teacher_forced` (context keys/values once, then all targets in one pass), here
        with gradients: the cache's buffers are written in place, which autograd records like any slice copy.
        """
        self._check_tokens(context_BTHW)
        self._check_tokens(targets_BTHW)
        if (context_BTHW == self.mask_token_id).any():
            raise ValueError("two-stream training: the context frames (input_ids) must not hold mask tokens")
        B, T = context_BTHW.shape[:2]
        cond_BTC = self.action_embeds(B, T, actions, latent_actions)
        kv_cache = self._context_cache(context_BTHW, cond_BTC)
        x_BTSC = self._embed(rearrange(targets_BTHW[:, 1:], "B T H W -> B T (H W)"), 1, _frames(cond_BTC, 1, T))
        x_BTSC = self.decoder(x_BTSC, kv_cache, targets=True)
        relevant_BTS = rearrange(targets_BTHW[:, 1:] == self.mask_token_id, "B T H W -> B T (H W)")
        return self._loss_at(x_BTSC, relevant_BTS, rearrange(labels_BTHW[:, 1:], "B T H W -> B T (H W)"))

    def _loss_at(self, x_BTSC: torch.Tensor, relevant_BTS: torch.Tensor, labels_BTS: torch.Tensor) -> STMaskGITOutput:
        """Read out the hidden states (B, T, S, C) where relevant (B, T, S) only -> factored CE and acc there."""
        factored_NVF = rearrange(self._readout(x_BTSC[relevant_BTS]), "N (F V) -> N V F",
                                 F=self.config.num_factored_vocabs)
        targets_N = labels_BTS[relevant_BTS]
        num_relevant = max(targets_N.numel(), 1)
        loss = factored_cross_entropy(factored_NVF, targets_N).sum() / num_relevant
        acc = factored_argmax_correct(factored_NVF, targets_N).sum().float() / num_relevant
        return STMaskGITOutput(loss=loss, acc=acc, logits=None)

    # ---------------------------------------------------------------- cached inference
    def new_kv_cache(self, capacity: int) -> TemporalKVCache:
        """An empty temporal KV cache with room for `capacity` frames."""
        return TemporalKVCache(self.config.num_layers, capacity)

    def forward_frames(self, x_BTHW: torch.Tensor, first_frame: int, kv_cache: TemporalKVCache,
                       targets: bool = False, commit: int = 0, readout: bool = True,
                       cond_BTC: Optional[torch.Tensor] = None) -> Optional[torch.Tensor]:
        """Run T frames at absolute positions first_frame.. against the frames in kv_cache.

        targets=False: the frames follow the cached ones (first_frame == kv_cache.length) and attend to them and
            causally to each other; `commit` of them (from the first) are then kept in the cache.
        targets=True: teacher-forced targets: frame first_frame + i attends to cached frames < first_frame + i and
            to itself (the cache holds frames 0..T-1 and first_frame is 1).
        cond_BTC: action embeddings of these T frames (B, T, C), from `action_embeds` of the whole window sliced
            to these frames (None: no action input).
        Returns factored logits (B, V, F, T, H, W), or None when readout is False.
        """
        self._check_tokens(x_BTHW, first_frame)
        if cond_BTC is not None and cond_BTC.shape[:2] != x_BTHW.shape[:2]:
            raise ValueError(f"cond_BTC {tuple(cond_BTC.shape)} does not match the frames {tuple(x_BTHW.shape)}")
        T = x_BTHW.shape[1]
        if targets and (first_frame != 1 or kv_cache.length != T):
            raise ValueError(f"teacher-forced targets 1..{T} need a cache of frames 0..{T - 1} and first_frame 1; "
                             f"got {kv_cache.length} cached frames and first_frame {first_frame}")
        if not targets and first_frame != kv_cache.length:
            raise ValueError(f"frames starting at {first_frame} must follow the {kv_cache.length} cached frames")
        return self._run_frames(x_BTHW, first_frame, kv_cache, targets, commit, readout, cond_BTC)

    def _run_frames(self, x_BTHW, first_frame, kv_cache, targets=False, commit=0, readout=True, cond_BTC=None):
        """forward_frames without the input checks (for ids the sampler produced: no device sync per step)."""
        x_BTSC = self._embed(rearrange(x_BTHW, "B T H W -> B T (H W)"), first_frame, cond_BTC)
        x_BTSC = self.decoder(x_BTSC, kv_cache, targets, kv_only=not readout and not targets)
        kv_cache.commit(commit)
        return self._factored(self._readout(x_BTSC)) if readout else None

    @torch.no_grad()
    def generate(self, prompt_BTHW: torch.Tensor, num_new_frames: int, maskgit_steps: int = 2,
                 temperature: float = 0.0, unmask_mode: str = "random", use_cache: bool = True,
                 generator: Optional[torch.Generator] = None, actions: Optional[torch.Tensor] = None,
                 latent_actions: Optional[torch.Tensor] = None,
                 control: bool = False) -> Tuple[torch.Tensor, torch.Tensor]:
        """Autoregressively generate frames after a prompt.

        prompt_BTHW: (B, T0, H, W) token ids; T0 + num_new_frames must be <= config.T.
        actions (B, T0 + n, D), latent_actions (B, T0 + n): per-frame action rows of the whole window (models with
        action inputs). control=False: only the prompt's rows are used (the challenge's rule; later frames get "no
        action" whatever the rows hold); control=True: all rows are played (driving the world).
        With the cache each MaskGIT step costs one frame's compute (plus one pass per finished frame to append it);
        without it every step recomputes the window, future frames masked (the published procedure).
        Returns (tokens (B, T0 + n, H, W): prompt then generated frames,
                 first-step factored logits of the generated frames (B, V, F, n, H, W)).
        """
        B, T0 = prompt_BTHW.shape[:2]
        total = T0 + num_new_frames
        if T0 < 1 or num_new_frames < 1:
            raise ValueError(f"need at least one prompt frame and one new frame, got {T0} and {num_new_frames}")
        if total > self.config.T:
            raise ValueError(f"cannot generate up to frame {total - 1}: the model has position embeddings for "
                             f"T = {self.config.T} frames (prompt {T0} + {num_new_frames} new > {self.config.T})")
        self._check_tokens(prompt_BTHW)
        cond_BTC = self.action_embeds(B, total, actions, latent_actions, total if control else T0)
        tokens_BTHW = torch.cat([prompt_BTHW, torch.full_like(prompt_BTHW[:, :1], self.mask_token_id)
                                 .expand(-1, num_new_frames, -1, -1)], dim=1)
        if use_cache:
            kv_cache = self.new_kv_cache(total)
            self._run_frames(prompt_BTHW, 0, kv_cache, commit=T0, readout=False,
                             cond_BTC=_frames(cond_BTC, 0, T0))
        all_logits = []
        for t in range(T0, total):
            if use_cache:
                def logits_fn(frame_BHW):
                    logits_BVF1HW = self._run_frames(frame_BHW.unsqueeze(1), t, kv_cache,
                                                     cond_BTC=_frames(cond_BTC, t, t + 1))
                    return logits_BVF1HW[:, :, :, 0]
            else:
                def logits_fn(frame_BHW):
                    window_BTHW = tokens_BTHW.clone()
                    window_BTHW[:, t] = frame_BHW
                    return rearrange(self._full_logits(window_BTHW, cond_BTC)[:, :, t], "B (F V) H W -> B V F H W",
                                     F=self.config.num_factored_vocabs)
            sample_BHW, logits_BVFHW = maskgit_sample(logits_fn, tokens_BTHW[:, t], self.mask_token_id, maskgit_steps,
                                                      temperature, unmask_mode, generator)
            tokens_BTHW[:, t] = sample_BHW
            all_logits.append(logits_BVFHW)
            if use_cache and t + 1 < total:
                self._run_frames(sample_BHW.unsqueeze(1), t, kv_cache, commit=1, readout=False,
                                 cond_BTC=_frames(cond_BTC, t, t + 1))
        return tokens_BTHW, torch.stack(all_logits, dim=3)

    @torch.no_grad()
    def teacher_forced(self, x_BTHW: torch.Tensor, maskgit_steps: int = 2, temperature: float = 0.0,
                       unmask_mode: str = "random", use_cache: bool = True,
                       generator: Optional[torch.Generator] = None, actions: Optional[torch.Tensor] = None,
                       latent_actions: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
        """The challenge protocol: predict each frame t = 1..T-1 of a window from ground-truth frames 0..t-1.

        x_BTHW: (B, T, H, W) ground-truth token ids, 2 <= T <= config.T.
        actions (B, T, D), latent_actions (B, T): per-frame action rows (models with action inputs). Target t knows
        rows < t only: the real action of frame t-1, not the latent action inferred from frame t itself.
        With the cache, frames 0..T-2 are computed once and all T-1 targets go through the model together in one
        pass per MaskGIT step (target t attends to the cached frames < t and to itself). Without it, every target
        and every step recomputes the whole window with frames >= t masked (the published evaluator).
        Returns (samples of frames 1..T-1 (B, T-1, H, W), first-step factored logits (B, V, F, T-1, H, W)).
        """
        B, T, H, W = x_BTHW.shape
        if T < 2:
            raise ValueError(f"teacher forcing needs windows of at least 2 frames, got {T}")
        self._check_tokens(x_BTHW)
        n = T - 1
        # context frames (all < every target that sees them) know all their rows; target t knows rows < t
        context_cond_BTC = self.action_embeds(B, T, actions, latent_actions, T)
        target_cond_BTC = self.action_embeds(B, T, actions, latent_actions, torch.arange(T))
        if use_cache:
            kv_cache = self._context_cache(x_BTHW, context_cond_BTC)

            def logits_fn(frames_NHW):
                frames_BnHW = rearrange(frames_NHW, "(B n) H W -> B n H W", B=B)
                logits_BVFnHW = self._run_frames(frames_BnHW, 1, kv_cache, targets=True,
                                                 cond_BTC=_frames(target_cond_BTC, 1, T))
                return rearrange(logits_BVFnHW, "B V F n H W -> (B n) V F H W")
        else:
            def logits_fn(frames_NHW):
                frames_BnHW = rearrange(frames_NHW, "(B n) H W -> B n H W", B=B)
                per_target = []
                for t in range(1, T):
                    window_BTHW = x_BTHW.clone()
                    window_BTHW[:, t] = frames_BnHW[:, t - 1]
                    window_BTHW[:, t + 1:] = self.mask_token_id
                    cond_BTC = self.action_embeds(B, T, actions, latent_actions, t)
                    per_target.append(self._full_logits(window_BTHW, cond_BTC)[:, :, t])
                return rearrange(torch.stack(per_target, dim=1), "B n (F V) H W -> (B n) V F H W",
                                 F=self.config.num_factored_vocabs)

        masked_NHW = torch.full((B * n, H, W), self.mask_token_id, dtype=x_BTHW.dtype, device=x_BTHW.device)
        samples_NHW, logits_NVFHW = maskgit_sample(logits_fn, masked_NHW, self.mask_token_id, maskgit_steps,
                                                   temperature, unmask_mode, generator)
        return (rearrange(samples_NHW, "(B n) H W -> B n H W", B=B),
                rearrange(logits_NVFHW, "(B n) V F H W -> B V F n H W", B=B))

    # ---------------------------------------------------------------- checkpoints
    def load_checkpoint_state_dict(self, state_dict: dict, source: str = "state dict") -> None:
        """Load weights, listing every missing / unexpected / wrongly shaped key in one clear error."""
        expected = self.state_dict()
        missing = sorted(set(expected) - set(state_dict))
        unexpected = sorted(set(state_dict) - set(expected))
        wrong_shape = [f"{k}: checkpoint {tuple(state_dict[k].shape)} vs model {tuple(v.shape)}"
                       for k, v in expected.items() if k in state_dict and state_dict[k].shape != v.shape]
        if missing or unexpected or wrong_shape:
            problems = [f"{what} ({len(keys)}): {keys[:8]}{' ...' if len(keys) > 8 else ''}"
                        for what, keys in (("missing keys", missing), ("unexpected keys", unexpected),
                                           ("shape mismatches", wrong_shape)) if keys]
            raise CheckpointError(f"{source}: weights do not match the model built from its config "
                                  f"(qk_norm={self.config.qk_norm}, num_layers={self.config.num_layers}, "
                                  f"d_model={self.config.d_model}): " + "; ".join(problems))
        self.load_state_dict(state_dict)

    def save_pretrained(self, save_directory: Union[str, Path], *, config=None, repo_id: Optional[str] = None,
                        push_to_hub: bool = False, model_card_kwargs: Optional[dict] = None, **push_to_hub_kwargs):
        """Write config.json + model.safetensors (the published layout) atomically.

        A new directory is written under a temporary name and renamed; in an existing directory each file is
        replaced atomically and other files are kept. `config` is ignored: the model's own GenieConfig is saved.
        """
        target = Path(save_directory)
        if target.exists() and not target.is_dir():
            raise NotADirectoryError(f"cannot save a checkpoint to {target}: it exists and is not a directory")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
        try:
            self.config.save(tmp / CONFIG_NAME)
            self._save_pretrained(tmp)
            update_manifest(tmp, (CONFIG_NAME, WEIGHTS_NAME))
            if target.exists():
                for name in (WEIGHTS_NAME, CONFIG_NAME):
                    os.replace(tmp / name, target / name)
                update_manifest(target, (CONFIG_NAME, WEIGHTS_NAME))
            else:
                os.replace(tmp, target)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        if push_to_hub:
            return self.push_to_hub(repo_id or target.name, model_card_kwargs=model_card_kwargs,
                                    **push_to_hub_kwargs)
        return None

    def _save_pretrained(self, save_directory: Path) -> None:
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        safetensors.torch.save_file(state, str(Path(save_directory) / WEIGHTS_NAME), metadata={"format": "pt"})

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path: Union[str, Path], *, revision: Optional[str] = None,
                        cache_dir=None, force_download: bool = False, local_files_only: bool = False,
                        token=None, map_location: str = "cpu", **kwargs) -> "STMaskGIT":
        """Load a checkpoint directory (config.json + model.safetensors) or a Hugging Face hub id.

        The config is parsed strictly (unknown keys are errors); the weights must match it key for key.
        The model is returned in eval mode.
        """
        if kwargs:
            raise TypeError(f"STMaskGIT.from_pretrained: unexpected arguments {sorted(kwargs)}")
        checkpoint_dir = resolve_checkpoint_dir(pretrained_model_name_or_path, revision=revision,
                                                cache_dir=cache_dir, force_download=force_download,
                                                local_files_only=local_files_only, token=token)
        verify_manifest(checkpoint_dir, [WEIGHTS_NAME])  # refuses silently corrupted weights
        config_path = checkpoint_dir / CONFIG_NAME
        config = GenieConfig.from_dict(load_json(config_path, "GENIE config"), source=str(config_path))
        model = cls(config)
        weights_path = checkpoint_dir / WEIGHTS_NAME
        try:
            state_dict = safetensors.torch.load_file(str(weights_path), device=str(map_location))
        except Exception as e:  # safetensors raises its own error types for truncated / non-safetensors files
            raise CheckpointError(f"{weights_path}: cannot read safetensors weights ({e})") from None
        model.load_checkpoint_state_dict(state_dict, source=str(weights_path))
        return model.eval()


def _frames(cond_BTC: Optional[torch.Tensor], start: int, end: int) -> Optional[torch.Tensor]:
    """Action embeddings of window frames start..end-1, or None for a model without action inputs."""
    return None if cond_BTC is None else cond_BTC[:, start:end]


def _looks_like_hub_id(name: str) -> bool:
    parts = name.split("/")
    return len(parts) == 2 and all(parts) and not name.startswith((".", "~")) and "\\" not in name


def resolve_checkpoint_dir(name_or_path: Union[str, Path], revision: Optional[str] = None, cache_dir=None,
                           force_download: bool = False, local_files_only: bool = False, token=None) -> Path:
    """A local checkpoint directory, or the hub cache directory of a downloaded hub id; clear errors otherwise."""
    path = Path(name_or_path)
    if path.is_dir():
        for name in (CONFIG_NAME, WEIGHTS_NAME):
            if not (path / name).is_file():
                raise FileNotFoundError(f"{path}: not a GENIE checkpoint directory ({name} is missing; expected "
                                        f"{CONFIG_NAME} and {WEIGHTS_NAME})")
        return path
    if path.exists():
        raise NotADirectoryError(f"{path}: a checkpoint must be a directory with {CONFIG_NAME} and {WEIGHTS_NAME}")
    if not _looks_like_hub_id(str(name_or_path)):
        raise FileNotFoundError(f"checkpoint directory not found: {path}")
    try:
        files = [hf_hub_download(str(name_or_path), name, revision=revision, cache_dir=cache_dir,
                                 force_download=force_download, local_files_only=local_files_only, token=token)
                 for name in (CONFIG_NAME, WEIGHTS_NAME)]
    except Exception as e:  # offline, unknown repo, no access, invalid id: all end the same way for the user
        raise FileNotFoundError(
            f"checkpoint {name_or_path!r} is not a local directory and could not be fetched from the Hugging Face "
            f"hub ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}). On a machine with internet, "
            f"download it with `huggingface-cli download {name_or_path} --local-dir <dir>` and pass that "
            f"directory instead.") from None
    return Path(files[0]).parent


def sincos_pos_embed(T: int, S: int, d_model: int, std: float = 0.02) -> torch.Tensor:
    """Fixed sin-cos positions (1, T, S, d_model) with per-element RMS `std`.

    Half of the channels encode the frame index, the other half the token index within the frame (row and column
    when S is a square, else the flat index), each as sin/cos pairs over geometrically spaced frequencies.
    """
    def encode(positions: torch.Tensor, dim: int) -> torch.Tensor:
        freqs = 1.0 / (100.0 ** (torch.arange(dim // 2, dtype=torch.float64) / max(dim // 2, 1)))
        angles = positions.double()[:, None] * freqs[None]
        return torch.cat([angles.sin(), angles.cos()], dim=-1)

    d_time = d_model // 2 // 2 * 2
    d_space = d_model - d_time
    side = math.isqrt(S)
    time_TC = encode(torch.arange(T), d_time)
    if side * side == S and d_space % 4 == 0:
        rows, cols = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
        space_SC = torch.cat([encode(rows.flatten(), d_space // 2), encode(cols.flatten(), d_space // 2)], dim=-1)
    else:
        space_SC = encode(torch.arange(S), d_space)
    space_SC = torch.nn.functional.pad(space_SC, (0, d_space - space_SC.shape[-1]))
    pos_TSC = torch.cat([time_TC[:, None].expand(T, S, d_time), space_SC[None].expand(T, S, d_space)], dim=-1)
    return (pos_TSC * (std * math.sqrt(2))).float().unsqueeze(0)
