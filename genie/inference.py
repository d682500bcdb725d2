"""Inference with the temporal KV cache: autoregressive generation and the challenge's teacher-forced evaluation.

Frame t depends only on frames <= t (causal temporal attention, per-frame spatial attention), so each layer's
temporal keys/values of the frames already known are kept (`TemporalKVCache`) and each MaskGIT step computes only
the frame being sampled. genie/reference.py holds the same computations without the cache (full recomputation,
the published procedure); the tests hold the two equal and benchmarks/bench_eval.py measures the difference.
"""
from typing import Optional, Tuple

import torch
from einops import rearrange

from genie.copy_head import LOGITS_LAYOUT, Prediction
from genie.model import action_embeds, check_tokens
from genie.sampling import GREEDY_TEMPERATURE, maskgit_sample
from genie.transformer import TemporalKVCache, TemporalMode


def _frames(cond_BTC: Optional[torch.Tensor], start: int, end: int) -> Optional[torch.Tensor]:
    """Action embeddings of window frames start..end-1, or None for a model without action inputs."""
    return None if cond_BTC is None else cond_BTC[:, start:end]


def run_frames(model, x_BTHW: torch.Tensor, first_frame: int, kv_cache: TemporalKVCache,
               mode: TemporalMode = TemporalMode.APPEND, commit: int = 0,
               cond_BTC: Optional[torch.Tensor] = None, with_mode: bool = False, greedy: bool = True):
    """Run T frames at absolute positions first_frame.. against the frames in kv_cache.

    mode APPEND / PREFILL: the frames follow the cached ones (first_frame == kv_cache.length); `commit` of them
    (from the first) are then kept in the cache. TARGETS: teacher-forced targets, frame first_frame + i attends to
    cached frames < first_frame + i and to itself (the cache holds frames 0..T-1 and first_frame is 1).
    cond_BTC: action embeddings of these T frames (B, T, C), `action_embeds` of the window sliced to them.
    Returns factored logits (B, V, F, T, H, W), or None in PREFILL mode; with_mode: a `Prediction` of them with
    the model's greedy tokens and their probabilities (B, T, H, W) where those are not the factor-wise argmax
    (greedy=False: without them, for a sampler at a temperature; `STMaskGIT.predict_frames`).
    Inputs are not checked (ids the sampler produced: no device sync per step); `check_frames` does that.
    """
    prediction = model.predict_frames(x_BTHW, cond_BTC, first_frame, mode, kv_cache, with_mode, greedy)
    kv_cache.commit(commit, x_BTHW)
    if prediction is None or with_mode:
        return prediction
    return prediction.logits


def frame_slice(prediction: Prediction, index) -> Prediction:
    """Frames `index` of a `Prediction` of windows (logits (B, V, F, T, H, W), mode (B, T, H, W), ...): int or
    slice."""
    return prediction.map(lambda v: v[:, :, :, index], lambda v: v[:, index])


def check_frames(model, x_BTHW: torch.Tensor, first_frame: int, kv_cache: TemporalKVCache, mode: TemporalMode,
                 cond_BTC: Optional[torch.Tensor] = None) -> None:
    """Clear errors for a `run_frames` call whose frames, cache and mode do not fit together."""
    check_tokens(model.config, x_BTHW, first_frame)
    if cond_BTC is not None and cond_BTC.shape[:2] != x_BTHW.shape[:2]:
        raise ValueError(f"cond_BTC {tuple(cond_BTC.shape)} does not match the frames {tuple(x_BTHW.shape)}")
    T = x_BTHW.shape[1]
    if mode is TemporalMode.TARGETS and (first_frame != 1 or kv_cache.length != T):
        raise ValueError(f"teacher-forced targets 1..{T} need a cache of frames 0..{T - 1} and first_frame 1; "
                         f"got {kv_cache.length} cached frames and first_frame {first_frame}")
    if mode is not TemporalMode.TARGETS and first_frame != kv_cache.length:
        raise ValueError(f"frames starting at {first_frame} must follow the {kv_cache.length} cached frames")


def context_cache(model, x_BTHW: torch.Tensor, cond_BTC: Optional[torch.Tensor]) -> TemporalKVCache:
    """Temporal keys/values of context frames 0..T-2 of a window (B, T, H, W), for targets 1..T-1."""
    n = x_BTHW.shape[1] - 1
    kv_cache = TemporalKVCache(model.config.num_layers, n)
    run_frames(model, x_BTHW[:, :n], 0, kv_cache, TemporalMode.PREFILL, commit=n, cond_BTC=_frames(cond_BTC, 0, n))
    return kv_cache


def generation_inputs(model, prompt_BTHW: torch.Tensor, num_new_frames: int, actions: Optional[torch.Tensor],
                      latent_actions: Optional[torch.Tensor], control: bool):
    """Checked inputs of a generation: (action embeddings (B, T0 + n, C) or None, the window's tokens
    (B, T0 + n, H, W) with the new frames masked). Without `control` only the prompt's action rows are known."""
    B, T0 = prompt_BTHW.shape[:2]
    if T0 < 1 or num_new_frames < 1:
        raise ValueError(f"need at least one prompt frame and one new frame, got {T0} and {num_new_frames}")
    total = T0 + num_new_frames
    if total > model.config.T:
        raise ValueError(f"cannot generate up to frame {total - 1}: the model has position embeddings for "
                         f"T = {model.config.T} frames (prompt {T0} + {num_new_frames} new > {model.config.T})")
    check_tokens(model.config, prompt_BTHW)
    cond_BTC = action_embeds(model, B, total, actions, latent_actions, total if control else T0)
    tokens_BTHW = torch.cat([prompt_BTHW, torch.full_like(prompt_BTHW[:, :1], model.mask_token_id)
                             .expand(-1, num_new_frames, -1, -1)], dim=1)
    return cond_BTC, tokens_BTHW


@torch.no_grad()
def generate_frames(model, prompt_BTHW: torch.Tensor, num_new_frames: int, maskgit_steps: int = 2,
             temperature: float = 0.0, unmask_mode: str = "random", generator: Optional[torch.Generator] = None,
             actions: Optional[torch.Tensor] = None, latent_actions: Optional[torch.Tensor] = None,
             control: bool = False, stall_ratio: Optional[float] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """Autoregressively generate frames after a prompt.

    prompt_BTHW: (B, T0, H, W) token ids; T0 + num_new_frames must be <= config.T.
    actions (B, T0 + n, D), latent_actions (B, T0 + n): per-frame action rows of the whole window (models with
    action inputs). control=False: only the prompt's rows are used (the challenge's rule; later frames get "no
    action" whatever the rows hold); control=True: all rows are played (driving the world).
    stall_ratio (opt-in decoding rule, None: off; needs T0 >= 2): once a generated frame changes at most this
    fraction of what the prompt's frames change per step (the share of tokens that differ from the frame before at
    the same position), that window's future is taken to have stopped moving, and every later frame repeats that
    one. A small model's greedy futures slow down and then decay in place (their few changing tokens make them worse
    than the frame they stopped at); this holds them where they stopped. Measured against the prompt's own motion,
    a scene that barely changes (a still camera) does not count as stalled.
    Each MaskGIT step costs one frame's compute, plus one pass per finished frame to append it to the cache.
    Returns (tokens (B, T0 + n, H, W): prompt then generated frames,
             first-step factored logits of the generated frames (B, V, F, n, H, W)).
    """
    cond_BTC, tokens_BTHW = generation_inputs(model, prompt_BTHW, num_new_frames, actions, latent_actions, control)
    T0, total = prompt_BTHW.shape[1], tokens_BTHW.shape[1]
    kv_cache = TemporalKVCache(model.config.num_layers, total)
    run_frames(model, prompt_BTHW, 0, kv_cache, TemporalMode.PREFILL, commit=T0, cond_BTC=_frames(cond_BTC, 0, T0))
    all_logits = []
    greedy = temperature <= GREEDY_TEMPERATURE
    if stall_ratio is not None:
        if not 0.0 < stall_ratio <= 1.0:
            raise ValueError(f"stall_ratio must be in (0, 1], got {stall_ratio}")
        if T0 < 2:
            raise ValueError("stall_ratio compares generated frames with the prompt's motion: it needs at least 2 "
                             f"prompt frames, got {T0}")
        stall_limit_B = stall_ratio * changed_share(prompt_BTHW[:, 1:], prompt_BTHW[:, :-1]).mean(dim=1)
    stalled_B = torch.zeros(tokens_BTHW.shape[0], dtype=torch.bool, device=tokens_BTHW.device)
    for t in range(T0, total):
        def logits_fn(frame_BHW):
            return frame_slice(run_frames(model, frame_BHW.unsqueeze(1), t, kv_cache,
                                          cond_BTC=_frames(cond_BTC, t, t + 1), with_mode=True,
                                          greedy=greedy), 0)

        sample_BHW, logits_BVFHW = maskgit_sample(logits_fn, tokens_BTHW[:, t], model.mask_token_id, maskgit_steps,
                                                  temperature, unmask_mode, generator)
        if stall_ratio is not None:
            sample_BHW, stalled_B = hold_stalled(sample_BHW, tokens_BTHW[:, t - 1], stalled_B, stall_limit_B)
        tokens_BTHW[:, t] = sample_BHW
        all_logits.append(logits_BVFHW)
        if t + 1 < total:
            run_frames(model, sample_BHW.unsqueeze(1), t, kv_cache, TemporalMode.PREFILL, commit=1,
                       cond_BTC=_frames(cond_BTC, t, t + 1))
    return tokens_BTHW, torch.stack(all_logits, dim=3)


def changed_share(frames: torch.Tensor, before: torch.Tensor) -> torch.Tensor:
    """(..., H, W) token frames and the frames before them -> (...,) the share of positions whose token changed."""
    return (frames != before).float().mean(dim=(-2, -1))


def hold_stalled(frame_BHW: torch.Tensor, before_BHW: torch.Tensor, stalled_B: torch.Tensor,
                 limit_B: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """`generate`'s stall rule for one new frame (B, H, W) after `before_BHW`: windows that stalled at an earlier
    frame repeat the frame before; the others keep their new frame, which stalls them from here on when it changes
    at most limit_B (B,) of the tokens. Returns (the frame to keep, stalled (B,) so far)."""
    kept_BHW = torch.where(stalled_B[:, None, None], before_BHW, frame_BHW)
    return kept_BHW, stalled_B | (changed_share(frame_BHW, before_BHW) <= limit_B)


def check_teacher_forced(model, x_BTHW: torch.Tensor) -> None:
    if x_BTHW.dim() == 4 and x_BTHW.shape[1] < 2:
        raise ValueError(f"teacher forcing needs windows of at least 2 frames, got {x_BTHW.shape[1]}")
    check_tokens(model.config, x_BTHW)


def target_action_embeds(model, x_BTHW: torch.Tensor, actions: Optional[torch.Tensor],
                         latent_actions: Optional[torch.Tensor]):
    """(context, target) action embeddings (B, T, C) of a teacher-forced window: context frames (all earlier than
    every target that sees them) know all their rows; target t knows rows < t, the real action of frame t-1 but
    not the latent action inferred from frame t itself."""
    B, T = x_BTHW.shape[:2]
    return (action_embeds(model, B, T, actions, latent_actions, T),
            action_embeds(model, B, T, actions, latent_actions, torch.arange(T)))


@torch.no_grad()
def teacher_forced(model, x_BTHW: torch.Tensor, maskgit_steps: int = 2, temperature: float = 0.0,
                   unmask_mode: str = "random", generator: Optional[torch.Generator] = None,
                   actions: Optional[torch.Tensor] = None,
                   latent_actions: Optional[torch.Tensor] = None) -> Tuple[torch.Tensor, torch.Tensor]:
    """The challenge protocol (docs/formats.md §5): predict each frame t = 1..T-1 of a window from ground-truth
    frames 0..t-1.

    x_BTHW: (B, T, H, W) ground-truth token ids, 2 <= T <= config.T.
    actions (B, T, D), latent_actions (B, T): per-frame action rows (models with action inputs), see
    `target_action_embeds`.
    Frames 0..T-2 are computed once and all T-1 targets go through the model together in one pass per MaskGIT
    step (target t attends to the cached frames < t and to itself).
    Returns (samples of frames 1..T-1 (B, T-1, H, W), first-step factored logits (B, V, F, T-1, H, W)).
    """
    check_teacher_forced(model, x_BTHW)
    B, T, H, W = x_BTHW.shape
    context_cond_BTC, target_cond_BTC = target_action_embeds(model, x_BTHW, actions, latent_actions)
    kv_cache = context_cache(model, x_BTHW, context_cond_BTC)

    greedy = temperature <= GREEDY_TEMPERATURE

    def logits_fn(frames_NHW):
        frames_BnHW = rearrange(frames_NHW, "(B n) H W -> B n H W", B=B)
        return targets_to_frames(run_frames(model, frames_BnHW, 1, kv_cache, TemporalMode.TARGETS,
                                            cond_BTC=_frames(target_cond_BTC, 1, T), with_mode=True,
                                            greedy=greedy))

    return sample_targets(model, logits_fn, B, T, x_BTHW, maskgit_steps, temperature, unmask_mode, generator)


def stack_frames(predictions) -> Prediction:
    """Per-frame `Prediction`s (logits (B, V, F, H, W), mode (B, H, W), ...) -> one `Prediction` of all the
    frames (logits (B, V, F, n, H, W), mode (B, n, H, W), ...)."""
    first = predictions[0]
    return Prediction(*(None if v is None else torch.stack([p[i] for p in predictions],
                                                           dim=3 if name in LOGITS_LAYOUT else 1)
                        for i, (name, v) in enumerate(zip(first._fields, first))))


def targets_to_frames(prediction: Prediction) -> Prediction:
    """A `Prediction` of the n targets of B windows (logits (B, V, F, n, H, W), mode (B, n, H, W), ...) as one of
    B * n frames (logits (B*n, V, F, H, W), mode (B*n, H, W), ...)."""
    return prediction.map(lambda v: rearrange(v, "B V F n H W -> (B n) V F H W"),
                          lambda v: rearrange(v, "B n H W ... -> (B n) H W ..."))


def sample_targets(model, logits_fn, B: int, T: int, x_BTHW: torch.Tensor, maskgit_steps: int, temperature: float,
                   unmask_mode: str, generator: Optional[torch.Generator]) -> Tuple[torch.Tensor, torch.Tensor]:
    """MaskGIT over the B * (T-1) fully masked targets of a teacher-forced window, given their logits function
    ((B*(T-1), H, W) -> (B*(T-1), V, F, H, W)); shapes as `teacher_forced` returns them."""
    H, W = x_BTHW.shape[2:]
    masked_NHW = torch.full((B * (T - 1), H, W), model.mask_token_id, dtype=x_BTHW.dtype, device=x_BTHW.device)
    samples_NHW, logits_NVFHW = maskgit_sample(logits_fn, masked_NHW, model.mask_token_id, maskgit_steps,
                                               temperature, unmask_mode, generator)
    return (rearrange(samples_NHW, "(B n) H W -> B n H W", B=B),
            rearrange(logits_NVFHW, "(B n) V F H W -> B V F n H W", B=B))


def window_inputs(model, tokens_nHW: torch.Tensor, actions_nD: Optional[torch.Tensor],
                  latent_n: torch.Tensor):
    """The window of a step: the n context frames and a masked new frame (1, n + 1, H, W), and its action embeddings
    (1, n + 1, C) or None. actions_nD: real action rows of the n context frames (NaN: unknown), latent_n: latent ids
    of the n + 1 frames (num_latent_actions: none)."""
    config = model.config
    n = len(tokens_nHW)
    window_BTHW = torch.cat([tokens_nHW, torch.full_like(tokens_nHW[:1], model.mask_token_id)])[None]
    actions_BTD = None
    if config.action_dim:
        actions_BTD = torch.cat([actions_nD, torch.full_like(actions_nD[:1], float("nan"))])[None].to(
            tokens_nHW.device)
    latent_BT = latent_n[None].to(tokens_nHW.device) if config.num_latent_actions else None
    return window_BTHW, action_embeds(model, 1, n + 1, actions_BTD, latent_BT, n + 1)


@torch.no_grad()
def next_frame(model, tokens_nHW: torch.Tensor, actions_nD: Optional[torch.Tensor],
               latent_n: torch.Tensor, cache: Optional[TemporalKVCache], maskgit_steps: int, temperature: float,
               generator: Optional[torch.Generator] = None):
    """Sample frame n after n <= T-1 context frames (n, H, W) at window positions 0..n-1.

    cache: the context's temporal keys/values from the step before, reused when it holds exactly these n frames
    at these positions (else recomputed). Returns (the new frame (H, W), a cache that holds the n + 1 frames, or
    None once the window is full)."""
    n = len(tokens_nHW)
    window_BTHW, cond_BTC = window_inputs(model, tokens_nHW, actions_nD, latent_n)
    cond = (lambda a, b: None) if cond_BTC is None else (lambda a, b: cond_BTC[:, a:b])
    if cache is None or cache.length != n:
        cache = TemporalKVCache(model.config.num_layers, model.config.T)
        run_frames(model, window_BTHW[:, :n], 0, cache, TemporalMode.PREFILL, commit=n, cond_BTC=cond(0, n))
    greedy = temperature <= GREEDY_TEMPERATURE

    def logits_fn(frame_BHW):
        return frame_slice(run_frames(model, frame_BHW[:, None], n, cache, cond_BTC=cond(n, n + 1), with_mode=True,
                                      greedy=greedy), 0)

    frame_BHW, _ = maskgit_sample(logits_fn, window_BTHW[:, n], model.mask_token_id, maskgit_steps, temperature,
                                  "random", generator)
    if n + 1 >= model.config.T:
        return frame_BHW[0], None
    run_frames(model, frame_BHW[:, None], n, cache, TemporalMode.PREFILL, commit=1, cond_BTC=cond(n, n + 1))
    return frame_BHW[0], cache
