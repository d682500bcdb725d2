"""Spatio-temporal transformer (Genie, arXiv 2402.15391, figure 4) with the published block semantics.

Each block: spatial attention over the S tokens of a frame (pre-norm `norm1`; opt-in 2-D rotary positions,
genie/rope.py), causal temporal attention over the frames at each spatial position (no norm before it, as
published; opt-in rotary positions by frame index), then an MLP (pre-norm `norm2`).

Frame t depends only on frames <= t, so inference keeps each layer's temporal keys/values of known frames in a
`TemporalKVCache` and runs only the frames it needs; `TemporalMode` says how the frames of a pass relate to the
cached ones (genie/inference.py).
"""
import enum
from typing import Optional

import torch
from einops import rearrange
from torch import nn
from torch.utils.checkpoint import checkpoint

from genie.attention import SelfAttention
from genie.config import GenieConfig
from genie.kv_cache import TemporalKVCache
from genie.rope import apply_rope, rope_tables


class TemporalMode(enum.Enum):
    """How the T frames of a pass attend over time.

    CAUSAL: a whole window from frame 0, causally; no cache.
    APPEND: frames that follow the cached ones: they attend to every cached frame and causally to each other, and
        their keys/values are written after the cached ones (kept only once the caller commits them).
    PREFILL: APPEND for frames whose outputs nobody reads (known context): the last layer only writes its
        keys/values and the pass returns None.
    TARGETS: teacher-forced targets 1..T over cached frames 0..T-1: target t attends to cached frames < t and to
        itself; nothing is written.
    """
    CAUSAL = "causal"
    APPEND = "append"
    PREFILL = "prefill"
    TARGETS = "targets"


def relu_squared(h: torch.Tensor) -> torch.Tensor:
    return torch.relu(h).square()


def swiglu(h: torch.Tensor) -> torch.Tensor:
    """SiLU(a) * b over the two halves of the last axis."""
    a, b = h.chunk(2, dim=-1)
    return nn.functional.silu(a) * b


# GenieConfig.mlp_activation -> the nonlinearity between fc1 and fc2
MLP_NONLINEARITIES = {"gelu": nn.functional.gelu, "relu2": relu_squared, "swiglu": swiglu}


class Mlp(nn.Module):
    """The block's MLP. `activation` "gelu" is the published one; "relu2" squares a ReLU (no new parameters);
    "swiglu" gates SiLU(a) * b, with fc1 producing both halves at 2/3 of the hidden width, so the parameters stay
    about those of the GELU MLP."""

    def __init__(self, d_model: int, mlp_ratio: float = 4.0, mlp_bias: bool = True, mlp_drop: float = 0.0,
                 activation: str = "gelu") -> None:
        super().__init__()
        hidden = int(d_model * mlp_ratio)
        gated = activation == "swiglu"
        if gated:
            hidden = int(hidden * 2 / 3)
        self.fc1 = nn.Linear(d_model, 2 * hidden if gated else hidden, bias=mlp_bias)
        self.act = MLP_NONLINEARITIES[activation]
        self.fc2 = nn.Linear(hidden, d_model, bias=mlp_bias)
        self.drop = nn.Dropout(mlp_drop)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.fc2(self.drop(self.act(self.fc1(x)))))


class STBlock(nn.Module):
    def __init__(self, config: GenieConfig) -> None:
        super().__init__()
        attn_kwargs = dict(d_model=config.d_model, num_heads=config.num_heads, qkv_bias=config.qkv_bias,
                           proj_bias=config.proj_bias, qk_norm=config.qk_norm, use_mup=config.use_mup,
                           attn_drop=config.attn_drop)
        # with qk_norm the published block has no pre-norms (q/k are normalized inside attention instead)
        self.norm1 = nn.Identity() if config.qk_norm else nn.LayerNorm(config.d_model, eps=1e-5)
        self.spatial_attn = SelfAttention(**attn_kwargs)
        self.temporal_attn = SelfAttention(**attn_kwargs)
        self.norm2 = nn.Identity() if config.qk_norm else nn.LayerNorm(config.d_model, eps=1e-5)
        self.mlp = Mlp(config.d_model, config.mlp_ratio, config.mlp_bias, config.mlp_drop, config.mlp_activation)
        self.rope = config.spatial_rope
        head_dim = config.d_model // config.num_heads
        if self.rope:  # not saved: the weights' layout is the same with or without
            cos_SD, sin_SD = rope_tables(config.H, config.W, head_dim)
            self.register_buffer("rope_cos_SD", cos_SD, persistent=False)
            self.register_buffer("rope_sin_SD", sin_SD, persistent=False)
        self.temporal_rope = config.temporal_rope
        if self.temporal_rope:  # a T x 1 grid: the first half of the channels turns with the frame, the rest stay
            cos_TD, sin_TD = rope_tables(config.T, 1, head_dim)
            self.register_buffer("rope_cos_TD", cos_TD, persistent=False)
            self.register_buffer("rope_sin_TD", sin_TD, persistent=False)

    def forward(self, x_BTSC: torch.Tensor, mode: TemporalMode = TemporalMode.CAUSAL,
                kv_cache: Optional[TemporalKVCache] = None, layer: int = 0,
                kv_only: bool = False, first_frame: int = 0) -> Optional[torch.Tensor]:
        """x (B, T, S, C) of frames first_frame.. -> (B, T, S, C); with kv_only (the last layer of a PREFILL pass)
        only this layer's temporal keys/values are written into the cache and None is returned."""
        B, T, S, C = x_BTSC.shape
        x_NSC = x_BTSC.reshape(B * T, S, C)
        rope = (self.rope_cos_SD, self.rope_sin_SD) if self.rope else None
        x_NSC = x_NSC + self.spatial_attn(self.norm1(x_NSC), rope=rope)

        x_MTC = rearrange(x_NSC, "(B T) S C -> (B S) T C", B=B)
        if kv_only:
            k, v = self.temporal_attn.project_kv(x_MTC)
            kv_cache.extend(layer, self.rotate_in_time(k, first_frame), v)
            return None
        x_MTC = x_MTC + self.temporal(x_MTC, mode, kv_cache, layer, first_frame)
        x_MTC = x_MTC + self.mlp(self.norm2(x_MTC))
        return rearrange(x_MTC, "(B S) T C -> B T S C", B=B)

    def rotate_in_time(self, x_MhTd: torch.Tensor, first_frame: int) -> torch.Tensor:
        """Queries or keys (B*S, heads, T, head_dim) of frames first_frame.. turned by their frame index (with
        temporal_rope; unchanged otherwise). Cached keys are stored turned, so each is turned once, by its own frame."""
        if not self.temporal_rope:
            return x_MhTd
        frames = slice(first_frame, first_frame + x_MhTd.shape[2])
        return apply_rope(x_MhTd, self.rope_cos_TD[frames], self.rope_sin_TD[frames])

    def temporal(self, x_MTC: torch.Tensor, mode: TemporalMode, kv_cache: Optional[TemporalKVCache],
                 layer: int, first_frame: int = 0) -> torch.Tensor:
        q, k, v = self.temporal_attn.project_qkv(x_MTC)
        q, k = self.rotate_in_time(q, first_frame), self.rotate_in_time(k, first_frame)
        if mode is TemporalMode.TARGETS:
            return self.temporal_attn.attend_targets(q, k, v, *kv_cache.cached(layer))
        if mode is TemporalMode.CAUSAL or kv_cache.length == 0:
            if mode is not TemporalMode.CAUSAL:
                kv_cache.extend(layer, k, v)
            return self.temporal_attn.attend(q, k, v, is_causal=True)
        num_cached, n = kv_cache.length, k.shape[2]
        k, v = kv_cache.extend(layer, k, v)
        mask = None
        if n > 1:  # new frame i sees every cached frame and new frames <= i
            mask = torch.ones(n, num_cached + n, dtype=torch.bool, device=q.device).tril(num_cached)
        return self.temporal_attn.attend(q, k, v, attn_mask=mask)


class STTransformer(nn.Module):
    def __init__(self, config: GenieConfig) -> None:
        super().__init__()
        self.layers = nn.ModuleList([STBlock(config) for _ in range(config.num_layers)])
        # activation checkpointing (train.py --gradient_checkpointing): keep only each block's input and recompute
        # the block in the backward pass, for larger batches in the same memory
        self.gradient_checkpointing = False

    def forward(self, x_BTSC: torch.Tensor, mode: TemporalMode = TemporalMode.CAUSAL,
                kv_cache: Optional[TemporalKVCache] = None, first_frame: int = 0) -> Optional[torch.Tensor]:
        """x (B, T, S, C) of frames first_frame.. -> (B, T, S, C), or None in PREFILL mode (only the cache is
        filled)."""
        if (kv_cache is None) != (mode is TemporalMode.CAUSAL):
            raise ValueError(f"temporal mode {mode.name} {'needs' if kv_cache is None else 'takes no'} KV cache")
        # only whole windows: the cached modes write keys/values in place, which a recomputation would repeat
        recompute = self.gradient_checkpointing and mode is TemporalMode.CAUSAL and torch.is_grad_enabled()
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            if recompute:
                x_BTSC = checkpoint(layer, x_BTSC, mode, first_frame=first_frame, use_reentrant=False)
            else:
                x_BTSC = layer(x_BTSC, mode, kv_cache, i, kv_only=mode is TemporalMode.PREFILL and i == last,
                               first_frame=first_frame)
        return x_BTSC
