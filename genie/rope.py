"""Rotary positions (RoPE): two-dimensional in the spatial attention (opt-in, `GenieConfig.spatial_rope`), and by
frame index in the temporal attention (`GenieConfig.temporal_rope`: the same tables for a T x 1 grid).

Each head's query and key channels are split in two: the first half is rotated by the token's row, the second by
its column, each half as standard RoPE (channel pairs i and i + n/2 turned by position * base^(-2i/n), n channels per
axis). The score of a query at (r, c) with a key at (r', c') then depends on the two positions only through
(r - r', c - c'), so a relation learned in one part of the frame (the neighbour a turning camera brings in from the
left) holds in every part. The absolute position embeddings stay; the tables are buffers that are not saved, so a
checkpoint's weights are the same with or without it. In time the column half of the channels never turns (every
frame is column 0), so the temporal attention keeps half of each head free of positions.
"""
from typing import Tuple

import torch

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
