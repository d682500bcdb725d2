"""Temporal key/value cache: what generation and the cached evaluation keep of the frames already known."""
from typing import List, Optional, Tuple

import torch


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
