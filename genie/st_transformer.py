"""Spatio-temporal transformer (Genie, arXiv 2402.15391, figure 4) with the published block semantics.

Each block: spatial attention over the S tokens of a frame (pre-norm `norm1`), causal temporal attention over
the frames at each spatial position (no norm before it, as published), then an MLP (pre-norm `norm2`).

Frame t depends only on frames <= t, so inference can keep each layer's temporal keys/values of known frames in a
`TemporalKVCache` and run only the frames it needs (see STMaskGIT.generate / STMaskGIT.teacher_forced).
"""
from typing import List, Optional, Tuple

import torch
from einops import rearrange
from torch import nn

from genie.attention import SelfAttention
from genie.config import GenieConfig


class Mlp(nn.Module):
    def __init__(self, d_model: int, mlp_ratio: float = 4.0, mlp_bias: bool = True, mlp_drop: float = 0.0) -> None:
        super().__init__()
        hidden = int(d_model * mlp_ratio)
        self.fc1 = nn.Linear(d_model, hidden, bias=mlp_bias)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, d_model, bias=mlp_bias)
        self.drop = nn.Dropout(mlp_drop)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.drop(self.fc2(self.drop(self.act(self.fc1(x)))))


class TemporalKVCache:
    """Per-layer temporal-attention keys and values of the frames known so far.

    Buffers are (B*S, heads, capacity, head_dim), allocated on first use; `length` frames are committed.
    `extend(layer, k, v)` writes the keys/values of the frames being computed into the free slots after `length`
    and returns keys/values of [committed frames, new frames]. The new frames become part of the cache only when
    `commit(n)` is called after the pass, so a frame still being sampled is recomputed at each MaskGIT step
    without growing the cache.
    """

    def __init__(self, num_layers: int, capacity: int) -> None:
        self.capacity = capacity
        self.length = 0
        self.keys: List[Optional[torch.Tensor]] = [None] * num_layers
        self.values: List[Optional[torch.Tensor]] = [None] * num_layers

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

    def commit(self, n: int) -> None:
        """Keep the first n frames of the last pass."""
        if self.length + n > self.capacity:
            raise ValueError(f"TemporalKVCache: committing {n} frames to {self.length} exceeds capacity "
                             f"{self.capacity}")
        self.length += n


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

    def forward(self, x_BTSC: torch.Tensor, kv_cache: Optional[TemporalKVCache] = None, layer: int = 0,
                targets: bool = False, kv_only: bool = False) -> Optional[torch.Tensor]:
        """x (B, T, S, C) -> (B, T, S, C).

        Without a cache the T frames attend causally to each other. With one, they are frames that follow the
        cached ones and also attend to all of them (their keys/values are written after the cached frames), or,
        with targets=True, they are teacher-forced targets 1..T over cached frames 0..T-1: target t attends to
        cached frames < t and to itself, and nothing is written.
        kv_only: only write this layer's temporal keys/values into the cache and return None (the last layer of
        a pass whose outputs are not needed, e.g. ground-truth context).
        """
        B, T, S, C = x_BTSC.shape
        x_NSC = x_BTSC.reshape(B * T, S, C)
        x_NSC = x_NSC + self.spatial_attn(self.norm1(x_NSC))

        x_MTC = rearrange(x_NSC, "(B T) S C -> (B S) T C", B=B)
        if kv_only:
            kv_cache.extend(layer, *self.temporal_attn.project_kv(x_MTC))
            return None
        x_MTC = x_MTC + self.temporal(x_MTC, kv_cache, layer, targets)
        x_MTC = x_MTC + self.mlp(self.norm2(x_MTC))
        return rearrange(x_MTC, "(B S) T C -> B T S C", B=B)

    def temporal(self, x_MTC: torch.Tensor, kv_cache: Optional[TemporalKVCache], layer: int,
                 targets: bool) -> torch.Tensor:
        q, k, v = self.temporal_attn.project_qkv(x_MTC)
        if kv_cache is None or (kv_cache.length == 0 and not targets):
            if kv_cache is not None:
                kv_cache.extend(layer, k, v)
            return self.temporal_attn.attend(q, k, v, is_causal=True)
        if targets:
            return self.temporal_attn.attend_targets(q, k, v, *kv_cache.cached(layer))
        num_cached, n = kv_cache.length, k.shape[2]
        k, v = kv_cache.extend(layer, k, v)
        mask = None
        if n > 1:  # new frame i sees every cached frame and new frames <= i
            mask = torch.ones(n, num_cached + n, dtype=torch.bool, device=q.device).tril(num_cached)
        return self.temporal_attn.attend(q, k, v, attn_mask=mask)


class STTransformerDecoder(nn.Module):
    def __init__(self, config: GenieConfig) -> None:
        super().__init__()
        self.layers = nn.ModuleList([STBlock(config) for _ in range(config.num_layers)])

    def forward(self, x_BTSC: torch.Tensor, kv_cache: Optional[TemporalKVCache] = None, targets: bool = False,
                kv_only: bool = False) -> Optional[torch.Tensor]:
        """kv_only: fill the cache with these frames' keys/values and skip what only their outputs need."""
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            x_BTSC = layer(x_BTSC, kv_cache, i, targets, kv_only=kv_only and i == last)
        return x_BTSC
