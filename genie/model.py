"""STMaskGIT: the GENIE dynamics model, loadable from the published GENIE_35M / GENIE_138M checkpoints.

token ids (B, T, H, W) -> embed (factored token embeddings + positions + optional action embeddings)
-> spatio-temporal transformer -> factored readout: logits (B, V, F, T, H, W), factor f of value v.
Opt-in (config.copy_radius): the readout is mixed with a pointer to the previous frame's tokens (genie/copy_head.py),
whose "logits" are then log-probabilities; every path that reads out passes the frame before each frame for it.
Parameter names, shapes and math follow docs/formats.md §3.

Predictions leave the model one of three ways: `forward`, its training loss (so that DDP sees one call): factored
cross entropy over the masked tokens of a collated batch (training/masking.py), read out at those tokens only;
`logits`, of a window, its inputs checked; and `predict_frames`, what the samplers read (genie/inference.py, with the
temporal KV cache; the uncached reference versions genie/reference.py). Checkpoint files are genie/checkpoint.py.
"""
import math
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Optional, Union

import torch
from einops import rearrange
from huggingface_hub import PyTorchModelHubMixin
from torch import nn

from common.config import ConfigError
from genie import checkpoint
from genie.actions import ActionConditioning
from genie.config import GenieConfig, TrainingRecipe
from genie.copy_head import CopyHead, Prediction, previous_frames
from genie.decoding import DecodingConfig, load_decoding
from genie.factorization import factorize_token_ids, unfactorize_token_ids
from genie.metrics import factored_argmax_correct, factored_cross_entropy
from genie.transformer import STTransformer, TemporalKVCache, TemporalMode

MUP_BASE_D_MODEL = 256  # the published muP base shape (set_mup_shapes hard-codes d_model 256)


@dataclass
class MaskGITBatch:
    """A collated training batch (training/masking.py); token ids are int64 (B, T, H, W)."""
    input_ids: torch.Tensor  # what the model sees: corrupted, the mask token where it is to predict
    labels: torch.Tensor  # the clean tokens
    actions: Optional[torch.Tensor] = None  # (B, T, D) float: the config's real action streams
    latent_actions: Optional[torch.Tensor] = None  # (B, T) int64: latent action ids

    def __post_init__(self):
        if self.input_ids.dim() != 4 or self.labels.shape != self.input_ids.shape:
            raise ValueError(f"MaskGITBatch: input_ids and labels must both be (B, T, H, W); got "
                             f"{tuple(self.input_ids.shape)} and {tuple(self.labels.shape)}")

    def to(self, device, non_blocking: bool = False) -> "MaskGITBatch":
        return MaskGITBatch(**{f.name: None if getattr(self, f.name) is None else
                               getattr(self, f.name).to(device, non_blocking=non_blocking) for f in fields(self)})


@dataclass
class LossOutput:
    loss: torch.Tensor  # factored CE summed over factors, mean over the predicted tokens
    acc: torch.Tensor  # argmax accuracy (every factor right) over the same tokens


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


class STMaskGIT(nn.Module, PyTorchModelHubMixin):
    def __init__(self, config: GenieConfig):
        super().__init__()
        self.config = config
        # `decoder` is the published parameter prefix of the transformer (decoder.layers.N...)
        self.decoder = STTransformer(config)
        self.pos_embed_TSC = nn.Parameter(torch.zeros(1, config.T, config.S, config.d_model))
        self.token_embed = FactorizedEmbedding(config.factored_vocab_size, config.num_factored_vocabs,
                                               config.d_model, config.mask_token_id)
        self.out_x_proj = nn.Linear(config.d_model, config.factored_vocab_size * config.num_factored_vocabs)
        # muP readout (mup.MuReadout with output_mult 1): the input is divided by d_model / base d_model
        self.readout_width_mult = config.d_model / MUP_BASE_D_MODEL if config.use_mup else None
        # only when enabled, so the published parameter layout is unchanged
        self.action_cond = ActionConditioning(config) if config.uses_actions else None
        self.copy_head = None if config.copy_radius is None else CopyHead(
            config.d_model, config.copy_radius, config.num_factored_vocabs, config.factored_vocab_size,
            config.mask_token_id, config.copy_match_input)
        self.decoding = DecodingConfig()  # how it is sampled (set_decoding); not a weight

    @property
    def mask_token_id(self) -> int:
        return self.config.mask_token_id

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

    def set_decoding(self, decoding: DecodingConfig) -> None:
        """Sample this model with `decoding` from now on (genie/decoding.py; saved with the checkpoint as
        decoding.json). Of its fields the model itself applies those of a copy head: copy_bias, added to the score
        of every previous-frame neighbour (e^bias times its copy weight against a new token; > 0 gives sharper
        futures that hold more of the previous frame), and greedy_tokens, how greedy decoding turns the mixture into
        tokens ("joint": its most probable whole token; "best_neighbour": a copy takes the single most weighted
        neighbour's token, `CopyHead.mode`). The samplers read the rest from `model.decoding`."""
        if self.copy_head is None and decoding.copy_bias:
            raise ConfigError("copy_bias needs a model with a copy head (config.copy_radius); this one has none")
        if self.copy_head is not None:
            self.copy_head.copy_bias = decoding.copy_bias
            self.copy_head.best_neighbour_copies = decoding.greedy_tokens == "best_neighbour"
        self.decoding = decoding

    # ---------------------------------------------------------------- predictions
    def logits(self, x_BTHW: torch.Tensor, actions: Optional[torch.Tensor] = None,
               latent_actions: Optional[torch.Tensor] = None,
               known_T: Union[int, torch.Tensor, None] = None) -> torch.Tensor:
        """Token ids of frames 0..T-1 (B, T, H, W), T <= config.T -> factored logits (B, V, F, T, H, W).

        actions / latent_actions / known_T: per-frame action inputs, see `action_embeds`.
        """
        check_tokens(self.config, x_BTHW)
        B, T = x_BTHW.shape[:2]
        return self.predict_frames(x_BTHW, action_embeds(self, B, T, actions, latent_actions, known_T),
                                   with_mode=False).logits

    def predict_frames(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor] = None, first_frame: int = 0,
                       mode: TemporalMode = TemporalMode.CAUSAL, kv_cache: Optional[TemporalKVCache] = None,
                       with_mode: bool = True, greedy: bool = True) -> Optional[Prediction]:
        """Frames first_frame.. (B, T, H, W) -> a `Prediction` of them (what the samplers read, genie/inference.py):
        factored logits (B, V, F, T, H, W) and, for a copy head's mixture, the greedy tokens and their probabilities
        (B, T, H, W) (not with greedy=False: a sampler at a temperature does not read them, `CopyHead.mode`) and the
        mixture's parts ((B, T, H, W, K + 1), (B, T, H, W, K), (B, V, F, T, H, W)), None where the model has no
        such part; with_mode=False: the logits alone.

        cond_BTC: action embeddings of these frames (B, T, C) or None, `action_embeds` of the window sliced to them.
        mode / kv_cache: how the frames attend over time (genie/transformer.py TemporalMode); the default is a whole
        window from frame 0 without a cache. PREFILL only writes the cache's keys/values and returns None;
        committing them is the caller's. Inputs are not checked (`check_tokens`): ids a sampler produced need no
        device sync per step.
        """
        sources_BTSK = self._copy_sources(x_BTHW, first_frame, mode, kv_cache)
        x_BTSC = self._hidden_states(x_BTHW, cond_BTC, first_frame, mode, kv_cache, sources_BTSK)
        if x_BTSC is None:
            return None
        H = self.config.H
        return self._readout(x_BTSC, sources_BTSK, with_mode, greedy).map(
            lambda v: rearrange(v, "B T (H W) V F -> B V F T H W", H=H),
            lambda v: rearrange(v, "B T (H W) ... -> B T H W ...", H=H))

    def _copy_sources(self, x_BTHW: torch.Tensor, first_frame: int = 0, mode: TemporalMode = TemporalMode.CAUSAL,
                      kv_cache: Optional[TemporalKVCache] = None) -> Optional[torch.Tensor]:
        """What the copy head may copy at each position of frames first_frame.. (B, T, H, W): the K neighbours
        (B, T, S, K) in the frame before each (the cache's committed frames; mask tokens before frame 0). None
        without a copy head or when nothing reads them (a PREFILL pass has no readout, so only the match input
        needs them)."""
        if self.copy_head is None or (mode is TemporalMode.PREFILL and not self.config.copy_match_input):
            return None
        if mode is TemporalMode.TARGETS:  # target first_frame + i follows cached frame first_frame + i - 1
            return self.copy_head.sources(kv_cache.frames(first_frame - 1, first_frame - 1 + x_BTHW.shape[1]))
        before_BHW = kv_cache.frames(first_frame - 1, first_frame)[:, 0] if first_frame > 0 else None
        return self.copy_head.sources(previous_frames(x_BTHW, self.mask_token_id, before_BHW))

    def _hidden_states(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor] = None, first_frame: int = 0,
                       mode: TemporalMode = TemporalMode.CAUSAL, kv_cache: Optional[TemporalKVCache] = None,
                       sources_BTSK: Optional[torch.Tensor] = None) -> Optional[torch.Tensor]:
        """Frames first_frame.. (B, T, H, W) -> final hidden states (B, T, S, C), before the readout (None in
        PREFILL mode). sources_BTSK: `_copy_sources` of these frames, embedded when the config sets
        copy_match_input."""
        T = x_BTHW.shape[1]
        x_BTSC = (self.token_embed(rearrange(x_BTHW, "B T H W -> B T (H W)"))
                  + self.pos_embed_TSC[:, first_frame:first_frame + T])
        if self.config.copy_match_input:
            x_BTSC = x_BTSC + self.copy_head.match_embedding(x_BTHW, sources_BTSK).to(x_BTSC.dtype)
        if cond_BTC is not None:
            x_BTSC = x_BTSC + cond_BTC.unsqueeze(2).to(x_BTSC.dtype)
        return self.decoder(x_BTSC, mode, kv_cache, first_frame)

    def _readout(self, x_NC: torch.Tensor, sources_NK: Optional[torch.Tensor] = None, with_mode: bool = True,
                 greedy: bool = True) -> Prediction:
        """Hidden states (..., C) -> a `Prediction` at the same positions: factored logits (..., V, F) (for a copy
        head, log-probabilities of the mixture with the neighbours sources_NK (..., K), genie/copy_head.py) and,
        with_mode, what decoding the mixture reads instead of the factor-wise logits: the most probable whole
        tokens (...) and their probabilities (...) (only when greedy decoding reads them: greedy=True) and the
        mixture's parts, from which a sampler at a temperature draws whole tokens."""
        x_scaled = x_NC if self.readout_width_mult is None else x_NC / self.readout_width_mult
        logits = rearrange(self.out_x_proj(x_scaled), "... (F V) -> ... V F", F=self.config.num_factored_vocabs)
        if self.copy_head is None:
            return Prediction(logits)
        if not with_mode:
            return Prediction(self.copy_head(logits, x_NC, sources_NK))
        ids = probs = None
        if greedy:
            mixture, ids, probs, log_weights = self.copy_head.forward_and_mode(logits, x_NC, sources_NK)
        else:
            mixture, log_weights = self.copy_head.forward_and_log_weights(logits, x_NC, sources_NK)
        return Prediction(mixture, ids, probs, log_weights, sources_NK, logits)

    # ---------------------------------------------------------------- the training loss
    def forward(self, batch: MaskGITBatch, recipe: Optional[TrainingRecipe] = None) -> LossOutput:
        """Factored CE and accuracy over the masked tokens of frames 1..T-1 of a collated batch (B, T, H, W), read
        out at those tokens only (the (F*V)-wide logits of every other token are most of a small model's step;
        genie/reference.py computes the same loss from every token's logits). In training mode a share
        recipe.self_reveal_ratio of the examples first has part of its masked tokens filled with the model's own
        guesses (`_reveal_own_predictions`); recipe None: the published recipe (no self-reveal)."""
        x_BTHW, labels_BTHW = batch.input_ids, batch.labels
        check_tokens(self.config, x_BTHW)
        B, T = x_BTHW.shape[:2]
        cond_BTC = action_embeds(self, B, T, batch.actions, batch.latent_actions)
        self_reveal_ratio = (recipe or TrainingRecipe()).self_reveal_ratio
        if self.training and self_reveal_ratio > 0:
            x_BTHW = self._reveal_own_predictions(x_BTHW, cond_BTC, self_reveal_ratio)
        relevant_BTS = rearrange(x_BTHW == self.mask_token_id, "B T H W -> B T (H W)")
        relevant_BTS[:, 0] = False  # frame 0 is always given
        factored_NVF = self._readout_at(x_BTHW, cond_BTC, relevant_BTS)
        targets_N = rearrange(labels_BTHW, "B T H W -> B T (H W)")[relevant_BTS]
        num_relevant = max(targets_N.numel(), 1)
        return LossOutput(loss=factored_cross_entropy(factored_NVF, targets_N).sum() / num_relevant,
                          acc=factored_argmax_correct(factored_NVF, targets_N).sum().float() / num_relevant)

    def _readout_at(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor],
                    where_BTS: torch.Tensor) -> torch.Tensor:
        """Factored logits (N, V, F) of the N positions `where_BTS` (B, T, S) of a window's frames x_BTHW (B, T, H, W)
        with action embeddings cond_BTC, read out there only."""
        sources_BTSK = self._copy_sources(x_BTHW)
        x_BTSC = self._hidden_states(x_BTHW, cond_BTC, sources_BTSK=sources_BTSK)
        return self._readout(x_BTSC[where_BTS], None if sources_BTSK is None else sources_BTSK[where_BTS],
                             with_mode=False).logits

    @torch.no_grad()
    def _reveal_own_predictions(self, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor],
                                ratio: float) -> torch.Tensor:
        """Training inputs (B, T, H, W) as a later MaskGIT step sees them: for a share `ratio` of the examples, a
        random share 1 - cos(pi/2 u), u ~ U(0, 1), of each frame's masked tokens is filled with the model's own
        one-pass prediction (each factor's argmax; one extra pass without gradients).

        At inference the tokens revealed after step 1 are the model's guesses (on the sample world ~11 % of them
        right), not the ground truth that published masking reveals; a model trained only on ground truth trusts
        them, and its second step gets worse than its first.
        """
        chosen_B = torch.rand(x_BTHW.shape[0], device=x_BTHW.device) < ratio
        if not chosen_B.any():
            return x_BTHW
        x_bTHW = x_BTHW[chosen_B]  # a copy
        masked_bTHW = x_bTHW == self.mask_token_id
        masked_bTHW[:, 0] = False
        logits_NVF = self._readout_at(x_bTHW, None if cond_BTC is None else cond_BTC[chosen_B],
                                      rearrange(masked_bTHW, "b T H W -> b T (H W)"))
        guesses_N = unfactorize_token_ids(logits_NVF.float().argmax(dim=1), self.config.num_factored_vocabs,
                                          self.config.factored_vocab_size)
        # 1 - MaskGIT's cosine schedule (genie.sampling.cosine_schedule) at a uniform progress
        share_bT11 = 1 - torch.cos(torch.rand(*masked_bTHW.shape[:2], 1, 1, device=x_BTHW.device) * math.pi / 2)
        reveal_bTHW = masked_bTHW & (torch.rand(masked_bTHW.shape, device=x_BTHW.device) < share_bT11)
        x_bTHW[masked_bTHW] = torch.where(reveal_bTHW[masked_bTHW], guesses_N, self.mask_token_id)
        return x_BTHW.index_put((chosen_B,), x_bTHW)

    # ---------------------------------------------------------------- checkpoints (genie/checkpoint.py)
    def save_pretrained(self, save_directory: Union[str, Path], *, config=None, repo_id: Optional[str] = None,
                        push_to_hub: bool = False, model_card_kwargs: Optional[dict] = None,
                        recipe: Optional[TrainingRecipe] = None, run_recipe: Optional[dict] = None,
                        decoding: Optional[DecodingConfig] = None, **push_to_hub_kwargs):
        """Write config.json (+ the training recipe, when given), model.safetensors, decoding.json (`decoding`, by
        default the model's own `self.decoding`) and recipe.json (`run_recipe`, when given) atomically; `config` is
        ignored (the model's own GenieConfig is saved)."""
        checkpoint.save_model(self, save_directory, recipe, run_recipe, decoding)
        if push_to_hub:
            return self.push_to_hub(repo_id or Path(save_directory).name, model_card_kwargs=model_card_kwargs,
                                    **push_to_hub_kwargs)
        return None

    @classmethod
    def from_pretrained(cls, pretrained_model_name_or_path: Union[str, Path], *, revision: Optional[str] = None,
                        cache_dir=None, force_download: bool = False, local_files_only: bool = False,
                        token=None, map_location: str = "cpu", **kwargs) -> "STMaskGIT":
        """Load a checkpoint directory (config.json + model.safetensors) or a Hugging Face hub id, in eval mode,
        set to decode as its decoding.json says (the published decoding when it has none)."""
        if kwargs:
            raise TypeError(f"STMaskGIT.from_pretrained: unexpected arguments {sorted(kwargs)}")
        checkpoint_dir = checkpoint.resolve_checkpoint_dir(
            pretrained_model_name_or_path, revision=revision, cache_dir=cache_dir, force_download=force_download,
            local_files_only=local_files_only, token=token)
        model = cls(checkpoint.load_config(checkpoint_dir))
        checkpoint.load_weights(model, checkpoint_dir, map_location)
        model.set_decoding(load_decoding(checkpoint_dir))
        return model.eval()


# ---------------------------------------------------------------- inputs (shared with genie/inference.py)
def check_tokens(config: GenieConfig, x_BTHW: torch.Tensor, first_frame: int = 0) -> None:
    """Clear errors for token ids (B, T, H, W) of frames first_frame.. that do not fit the model of `config`
    (shape, frame range, dtype, id range)."""
    if x_BTHW.dim() != 4 or x_BTHW.shape[2] * x_BTHW.shape[3] != config.S:
        raise ValueError(f"expected token ids of shape (B, T, H, W) with H*W = S = {config.S}, "
                         f"got {tuple(x_BTHW.shape)}")
    if first_frame + x_BTHW.shape[1] > config.T:
        raise ValueError(f"frames {first_frame}..{first_frame + x_BTHW.shape[1] - 1} requested, but the model "
                         f"has position embeddings for T = {config.T} frames only")
    if x_BTHW.is_floating_point():
        raise ValueError(f"token ids must be integers, got {x_BTHW.dtype}")
    if ((x_BTHW < 0) | (x_BTHW > config.mask_token_id)).any():
        raise ValueError(f"token ids must be in [0, {config.image_vocab_size}) or the mask token "
                         f"{config.mask_token_id}; got values in [{x_BTHW.min().item()}, {x_BTHW.max().item()}]")


def action_embeds(model: STMaskGIT, B: int, T: int, actions: Optional[torch.Tensor] = None,
                  latent_actions: Optional[torch.Tensor] = None,
                  known_T: Union[int, torch.Tensor, None] = None) -> Optional[torch.Tensor]:
    """Action embeddings (B, T, C) of window frames 0..T-1, or None for a model without action inputs.

    actions (B, T, D) float, latent_actions (B, T) ids: per-frame rows as in the dataset (genie/actions.py).
    known_T: how many leading rows each frame may use (int or (T,)); None: all of them.
    A model without action inputs raises when given actions.
    """
    if model.action_cond is None:
        if actions is not None or latent_actions is not None:
            raise ValueError("this model has no action inputs (its config sets neither action_names nor "
                             "num_latent_actions); do not pass actions or latent_actions")
        return None
    model.action_cond.check_inputs(actions, latent_actions, B, T)
    device = model.pos_embed_TSC.device
    return model.action_cond(B, T, actions, latent_actions, T if known_T is None else known_T, device)


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
