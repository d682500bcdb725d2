"""The copy ceiling: how close free-running futures made only of whole-token copies can get to the true future.

The previous-frame pointer (genie/copy_head.py) makes greedy futures that are almost all copies: every token of a
generated frame is some neighbour's token in the frame before it. This measures the best such futures, chosen
knowing the truth, as a diagnostic of how much of a model's gap to the truth is its choice of copies and how much is
copying itself (`python diagnose.py copy_ceiling`, which scores them like a model's rollouts).

Each frame after the prompt is made from the ceiling's own frame before it (so its errors compound as a rollout's
do): every token is copied from one of the (2r+1)^2 neighbours of its position, the frame's edge tokens extended
outwards, namely the neighbour whose code is nearest to the true token's: fewest differing bits, which for a
lookup-free code (the bits are its latent's signs) is the squared latent distance / 4; ties go to the smaller
displacement. With block > 1 all positions of a block x block tile share one displacement, the one with the least
distance summed over the tile (block = the frame's side: one shift of the whole frame), which asks how fine a
motion field a copy model must predict.
"""
from typing import Tuple

import torch
from einops import rearrange, repeat


def code_distances(a: torch.Tensor, b: torch.Tensor, num_bits: int) -> torch.Tensor:
    """How many of the num_bits low bits of token ids a and b (int64, broadcast shapes) differ."""
    diff = torch.bitwise_xor(a, b)
    return sum((diff >> bit) & 1 for bit in range(num_bits))


def neighbours(frame_BHW: torch.Tensor, radius: int) -> torch.Tensor:
    """Token ids (B, H, W) -> the (2r+1)^2 neighbours of every position (B, H, W, K), row-major offsets from
    (-r, -r); positions outside the frame take the nearest edge token."""
    H, W = frame_BHW.shape[-2:]
    rows = torch.arange(H, device=frame_BHW.device)
    cols = torch.arange(W, device=frame_BHW.device)
    shifted = [frame_BHW[:, (rows + dy).clamp(0, H - 1)][:, :, (cols + dx).clamp(0, W - 1)]
               for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)]
    return torch.stack(shifted, dim=-1)


def best_copies(prev_BHW: torch.Tensor, true_BHW: torch.Tensor, radius: int, block: int,
                num_bits: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """The frame (B, H, W) of copies from prev_BHW nearest to true_BHW (module doc), and where its token is the
    true one (B, H, W) bool. H and W must be multiples of block."""
    B, H, W = true_BHW.shape
    sources_BHWK = neighbours(prev_BHW, radius)
    offsets = range(-radius, radius + 1)
    displacement_K = torch.tensor([abs(dy) + abs(dx) for dy in offsets for dx in offsets], device=true_BHW.device)
    # any difference of one bit outweighs the largest difference in displacement (4r)
    cost_BHWK = code_distances(sources_BHWK, true_BHW.unsqueeze(-1), num_bits) * (4 * radius + 1) + displacement_K
    if block > 1:
        tile_cost = rearrange(cost_BHWK, "B (h p) (w q) K -> B h w K (p q)", p=block, q=block).sum(-1)
        choice_BHW = repeat(tile_cost.argmin(-1), "B h w -> B (h p) (w q)", p=block, q=block)
    else:
        choice_BHW = cost_BHWK.argmin(-1)
    copies_BHW = sources_BHWK.gather(-1, choice_BHW.unsqueeze(-1)).squeeze(-1)
    return copies_BHW, copies_BHW == true_BHW


def ceiling_rollout(x_BTHW: torch.Tensor, num_prompt_frames: int, radius: int, block: int,
                    num_bits: int) -> Tuple[torch.Tensor, torch.Tensor]:
    """Windows (B, T, H, W) -> the same windows with frames >= num_prompt_frames replaced by the copy ceiling's
    frames (B, T, H, W), and how many of those tokens are the true ones per window (B,)."""
    out_BTHW = x_BTHW.clone()
    exact_B = torch.zeros(x_BTHW.shape[0], dtype=torch.long, device=x_BTHW.device)
    for t in range(num_prompt_frames, x_BTHW.shape[1]):
        out_BTHW[:, t], exact_BHW = best_copies(out_BTHW[:, t - 1], x_BTHW[:, t], radius, block, num_bits)
        exact_B += exact_BHW.flatten(1).sum(-1)
    return out_BTHW, exact_B
