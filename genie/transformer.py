"""The spatio-temporal transformer (Genie, arXiv 2402.15391, figure 4) with the published block semantics: its
attention, rotary positions and the temporal key/value cache that inference keeps.

Each block: spatial attention over the S tokens of a frame (pre-norm `norm1`; opt-in 2-D rotary positions),
causal temporal attention over the frames at each spatial position (no norm before it, as published; opt-in rotary
positions by frame index), then a GELU MLP (pre-norm `norm2`).

Attention keeps the published parameter layout (docs/formats.md §3): `qkv` (3d, d) whose output splits as
(3, heads, head_dim), `proj` (d, d) and, with qk_norm, one LayerNorm `norm` over head_dim applied to both q and k.
The published weights were trained with xformers' memory-efficient attention: q and k are normalized first and the
softmax scale is applied afterwards inside the kernel, which is what `scale=` of scaled_dot_product_attention does
here. attn_drop (0 in every published config) drops attention weights in training.

Rotary positions: each head's query and key channels are split in two, the first half turned by the token's row,
the second by its column (standard RoPE per axis), so a score depends on two positions only through their offset.
In time the same tables serve a T x 1 grid: the column half never turns, so half of each head stays free of
positions. The tables are buffers that are not saved: a checkpoint's weights are the same with or without them.

Frame t depends only on frames <= t, so inference keeps each layer's temporal keys/values of known frames in a
`TemporalKVCache` and runs only the frames it needs; `TemporalMode` says how the frames of a pass relate to the
cached ones (genie/inference.py).
"""
import enum
from typing import List, Optional, Tuple

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn
from torch.utils.checkpoint import checkpoint

from genie.config import GenieConfig


# ---------------------------------------------------------------- rotary positions
# 16 positions per axis: base 100 spreads the wavelengths from 2*pi to ~470 tokens, where 10,000 would leave
# half of the channel pairs turning by less than a degree across the whole frame
ROPE_BASE = 100.0


def rope_tables(H: int, W: int, head_dim: int, base: float = ROPE_BASE) -> Tuple[torch.Tensor, torch.Tensor]:
    """cos and sin, each (H * W, head_dim), for tokens in row-major order (the token grid's flattening)."""
    if head_dim % 4:
        raise ValueError(f"2-D rotary positions need a head width divisible by 4, got {head_dim}")
    n = head_dim // 2  # channels per axis
    freqs_F = base ** (-torch.arange(0, n, 2, dtype=torch.float64) / n)
    rows_S, cols_S = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    angles_SAF = torch.stack([rows_S.flatten(), cols_S.flatten()], dim=-1).double()[:, :, None] * freqs_F
    angles_SD = angles_SAF[:, :, None, :].expand(-1, -1, 2, -1).flatten(1)  # (axis, half, pair) -> head_dim
    return angles_SD.cos().float(), angles_SD.sin().float()


def apply_rope(x_BhSd: torch.Tensor, cos_SD: torch.Tensor, sin_SD: torch.Tensor) -> torch.Tensor:
    """Rotate queries or keys (..., S, head_dim) by their tokens' positions; same shape and dtype."""
    halves = x_BhSd.unflatten(-1, (2, 2, -1))  # (axis, half, pair)
    rotated = torch.stack((-halves[..., 1, :], halves[..., 0, :]), dim=-2).flatten(-3)
    return x_BhSd * cos_SD.to(x_BhSd.dtype) + rotated * sin_SD.to(x_BhSd.dtype)


# ---------------------------------------------------------------- attention
def attention_scale(head_dim: int, use_mup: bool) -> float:
    """Softmax scale: head_dim^-0.5, or 8 / head_dim under muP (equal at head_dim 64)."""
    return 8 / head_dim if use_mup else head_dim ** -0.5


# bf16 on CPU, sequences of at most this many keys (the temporal attention) take the written-out path; longer ones
# are faster in torch's fused kernel
CPU_BF16_MATH_MAX_KEYS = 64


class SelfAttention(nn.Module):
    def __init__(self, d_model: int, num_heads: int, qkv_bias: bool = False, proj_bias: bool = True,
                 qk_norm: bool = False, use_mup: bool = False, attn_drop: float = 0.0) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.head_dim = d_model // num_heads
        self.scale = attention_scale(self.head_dim, use_mup)
        self.attn_drop = attn_drop
        self.qkv = nn.Linear(d_model, 3 * d_model, bias=qkv_bias)
        self.proj = nn.Linear(d_model, d_model, bias=proj_bias)
        self.qk_norm = qk_norm
        if qk_norm:
            self.norm = nn.LayerNorm(self.head_dim, eps=1e-5)
        # bf16 on CPU: the written-out path for short sequences (`_attend_bf16_cpu`); `set_cpu_bf16_math` turns it
        # off per model (benchmarks/bench_train.py compares the two)
        self.cpu_bf16_math = True

    def project_qkv(self, x_BNC: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(B, N, C) -> q, k, v, each (B, heads, N, head_dim)."""
        qkv_3BhNd = rearrange(self.qkv(x_BNC), "B N (three h d) -> three B h N d", three=3, h=self.num_heads)
        q, k, v = qkv_3BhNd.unbind(0)
        if self.qk_norm:
            # under autocast LayerNorm runs in fp32; the attention kernel wants q, k, v in one dtype
            q = self.norm(q).to(v.dtype)
            k = self.norm(k).to(v.dtype)
        return q, k, v

    def project_kv(self, x_BNC: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """Keys and values only, each (B, heads, N, head_dim): skips the query third of the qkv projection."""
        C = x_BNC.shape[-1]
        bias = None if self.qkv.bias is None else self.qkv.bias[C:]
        kv_2BhNd = rearrange(F.linear(x_BNC, self.qkv.weight[C:], bias), "B N (two h d) -> two B h N d", two=2,
                             h=self.num_heads)
        k, v = kv_2BhNd.unbind(0)
        if self.qk_norm:
            k = self.norm(k).to(v.dtype)
        return k, v

    def attend(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, attn_mask: Optional[torch.Tensor] = None,
               is_causal: bool = False) -> torch.Tensor:
        """q (B, heads, Nq, head_dim), k and v (B, heads, Nk, head_dim) -> projected output (B, Nq, C).

        attn_mask: optional bool (Nq, Nk), True where a query may attend to a key.
        """
        dropout_p = self.attn_drop if self.training else 0.0
        if (self.cpu_bf16_math and q.device.type == "cpu" and q.dtype == torch.bfloat16
                and k.shape[-2] <= CPU_BF16_MATH_MAX_KEYS):
            x_BhNd = self._attend_bf16_cpu(q, k, v, attn_mask, is_causal, dropout_p)
        else:
            x_BhNd = F.scaled_dot_product_attention(q, k, v, attn_mask=attn_mask, is_causal=is_causal,
                                                    dropout_p=dropout_p, scale=self.scale)
        return self.proj(rearrange(x_BhNd, "B h N d -> B N (h d)"))

    def _attend_bf16_cpu(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor,
                         attn_mask: Optional[torch.Tensor], is_causal: bool, dropout_p: float) -> torch.Tensor:
        """Attention written out for bf16 on CPU: (B, h, Nq, d) -> (B, h, Nq, d).

        torch's fused CPU attention kernel is slow in bf16 for many short sequences (the temporal attention: B*S
        sequences of T frames; ~3x slower forward + backward at T = 16), while for the spatial attention (S = 256
        keys) it is the faster one; two bf16 matmuls with an fp32 softmax in between use the CPU's native bf16 dot
        products instead (benchmarks/bench_train.py --mixed_precision compare).
        """
        scores = (q @ k.transpose(-1, -2)).float() * self.scale
        if is_causal:
            future = torch.ones(scores.shape[-2:], dtype=torch.bool, device=q.device).triu(1)  # top-left, as SDPA
            scores = scores.masked_fill(future, float("-inf"))
        if attn_mask is not None:
            scores = scores.masked_fill(~attn_mask, float("-inf"))
        probs = F.dropout(scores.softmax(dim=-1), p=dropout_p) if dropout_p else scores.softmax(dim=-1)
        return probs.to(v.dtype) @ v

    def forward(self, x_BNC: torch.Tensor, causal: bool = False,
                rope: Optional[Tuple[torch.Tensor, torch.Tensor]] = None) -> torch.Tensor:
        """(B, N, C) -> (B, N, C); rope: optional (cos, sin) tables (N, head_dim) that rotate q and k (`rope_tables`)."""
        q, k, v = self.project_qkv(x_BNC)
        if rope is not None:
            q, k = apply_rope(q, *rope), apply_rope(k, *rope)
        return self.attend(q, k, v, is_causal=causal)

    def attend_targets(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, context_k: torch.Tensor,
                       context_v: torch.Tensor) -> torch.Tensor:
        """Teacher-forced targets: target i attends to context positions 0..i and to itself only.

        q, k, v: (B, heads, n, head_dim) of the n targets; context_k, context_v: (B, heads, n, head_dim).
        Returns the projected output (B, n, C). Equal to scaled_dot_product_attention over
        cat([context, targets]) with mask [tril, eye]; written out because that needs a (B, heads, 2n, head_dim)
        copy of the keys and values at every step and the slow masked kernel.
        """
        n = q.shape[2]
        q, k = q.float() * self.scale, k.float()  # fp32 scores and softmax, like the fused kernels (no-op in fp32)
        future = torch.ones(n, n, dtype=torch.bool, device=q.device).triu(1)
        scores_ctx = (q @ context_k.float().transpose(-1, -2)).masked_fill_(future, float("-inf"))
        score_self = (q * k).sum(-1, keepdim=True)
        probs = torch.cat([scores_ctx, score_self], dim=-1).softmax(dim=-1)
        x_BhNd = (probs[..., :n] @ context_v.float() + probs[..., n:] * v.float()).to(v.dtype)
        return self.proj(rearrange(x_BhNd, "B h N d -> B N (h d)"))


def set_cpu_bf16_math(model: nn.Module, enabled: bool) -> None:
    """Choose, for every attention layer of `model`, the written-out bf16 CPU path (True) or torch's fused kernel."""
    for module in model.modules():
        if isinstance(module, SelfAttention):
            module.cpu_bf16_math = enabled


# ---------------------------------------------------------------- the temporal key/value cache
class TemporalKVCache:
    """Per-layer temporal-attention keys and values of the frames known so far.

    Buffers are (B*S, heads, capacity, head_dim), allocated on first use; `length` frames are committed.
    `extend(layer, k, v)` writes the keys/values of the frames being computed into the free slots after `length`
    and returns keys/values of [committed frames, new frames]. The new frames become part of the cache only when
    `commit(n)` is called after the pass, so a frame still being sampled is recomputed at each MaskGIT step
    without growing the cache. `commit(n, tokens)` also keeps the committed frames' token ids, which the copy head
    (genie/copy_head.py) reads as the frame before the next one.
    """

    def __init__(self, num_layers: int, capacity: int) -> None:
        self.capacity = capacity
        self.length = 0
        self.keys: List[Optional[torch.Tensor]] = [None] * num_layers
        self.values: List[Optional[torch.Tensor]] = [None] * num_layers
        self.tokens: Optional[torch.Tensor] = None  # (B, capacity, H, W) token ids of committed frames

    def extend(self, layer: int, k: torch.Tensor, v: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """k, v: (B*S, heads, n, head_dim) of the new frames -> keys, values (B*S, heads, length + n, head_dim)."""
        end = self.length + k.shape[2]
        if end > self.capacity:
            raise ValueError(f"TemporalKVCache: {self.length} cached + {k.shape[2]} new frames exceed its capacity "
                             f"of {self.capacity}")
        if self.keys[layer] is None:
            M, h, _, d = k.shape
            self.keys[layer] = k.new_empty(M, h, self.capacity, d)
            self.values[layer] = v.new_empty(M, h, self.capacity, d)
        if self.keys[layer].shape[0] != k.shape[0]:
            raise ValueError(f"TemporalKVCache holds {self.keys[layer].shape[0]} sequences (batch * S), "
                             f"got {k.shape[0]}")
        self.keys[layer][:, :, self.length:end] = k
        self.values[layer][:, :, self.length:end] = v
        return self.keys[layer][:, :, :end], self.values[layer][:, :, :end]

    def cached(self, layer: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """Committed keys, values of a layer: (B*S, heads, length, head_dim)."""
        return self.keys[layer][:, :, :self.length], self.values[layer][:, :, :self.length]

    def commit(self, n: int, tokens_BTHW: Optional[torch.Tensor] = None) -> None:
        """Keep the first n frames of the last pass (and of tokens_BTHW, that pass's token ids, when given)."""
        if self.length + n > self.capacity:
            raise ValueError(f"TemporalKVCache: committing {n} frames to {self.length} exceeds capacity "
                             f"{self.capacity}")
        if tokens_BTHW is not None and n > 0:
            if self.tokens is None:
                B, _, H, W = tokens_BTHW.shape
                self.tokens = tokens_BTHW.new_empty(B, self.capacity, H, W)
            self.tokens[:, self.length:self.length + n] = tokens_BTHW[:, :n]
        self.length += n

    def frames(self, start: int, end: int) -> torch.Tensor:
        """Token ids (B, end - start, H, W) of committed frames start..end-1 (committed with their tokens)."""
        if self.tokens is None or not 0 <= start <= end <= self.length:
            raise ValueError(f"TemporalKVCache: frames {start}..{end - 1} requested, {self.length} committed"
                             + ("" if self.tokens is not None else " without their token ids"))
        return self.tokens[:, start:end]


# ---------------------------------------------------------------- blocks
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


class Mlp(nn.Module):
    """The block's MLP: fc1, GELU, fc2 (published)."""

    def __init__(self, d_model: int, mlp_ratio: float = 4.0, mlp_bias: bool = True, mlp_drop: float = 0.0) -> None:
        super().__init__()
        hidden = int(d_model * mlp_ratio)
        self.fc1 = nn.Linear(d_model, hidden, bias=mlp_bias)
        self.fc2 = nn.Linear(hidden, d_model, bias=mlp_bias)
        self.drop = nn.Dropout(mlp_drop)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.fc2(self.drop(F.gelu(self.fc1(x)))))


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
        self.mlp = Mlp(config.d_model, config.mlp_ratio, config.mlp_bias, config.mlp_drop)
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
