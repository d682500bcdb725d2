"""MAGVIT2 (Open-MAGVIT2) convolutional encoder and decoder with the published parameter names (docs/formats.md §4).

Encoder: conv_in -> per level i: down.i.block.j ResBlocks, down.i.downsample (stride-2 conv, not on the last level)
-> mid_block -> norm_out -> swish -> conv_out (1x1 to z_channels).
Decoder: conv_in -> mid_block -> per level i from last to 0: up.i.block.j ResBlocks, then for i > 0
up.i.upsample (conv to 4x channels + DCR depth-to-space) -> norm_out -> swish -> conv_out.
"""
import torch
import torch.nn as nn
import torch.nn.functional as F
from einops import rearrange

from magvit2.config import VQConfig


def group_norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(32, channels, eps=1e-6)


def depth_to_space(x_BCHW: torch.Tensor, block_size: int = 2) -> torch.Tensor:
    """(B, C, H, W) -> (B, C / b^2, H * b, W * b) in DCR order (depth-column-row, as TensorFlow / Open-MAGVIT2).

    Input channel (i * b + j) * C' + c goes to output channel c, pixel (h * b + i, w * b + j). nn.PixelShuffle
    uses the CRD order (input channel c * b^2 + i * b + j) and would scramble the published weights.
    """
    return rearrange(x_BCHW, "B (i j C) H W -> B C (H i) (W j)", i=block_size, j=block_size)


class ResBlock(nn.Module):
    """Pre-activation residual block: GN -> swish -> conv3x3 -> GN -> swish -> conv3x3, 1x1 shortcut if in != out."""

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        self.norm1 = group_norm(in_channels)
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False)
        self.norm2 = group_norm(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, padding=1, bias=False)
        if in_channels != out_channels:
            self.nin_shortcut = nn.Conv2d(in_channels, out_channels, 1, bias=False)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        h = self.conv1(F.silu(self.norm1(x_BCHW)))
        h = self.conv2(F.silu(self.norm2(h)))
        shortcut = self.nin_shortcut(x_BCHW) if hasattr(self, "nin_shortcut") else x_BCHW
        return shortcut + h


class Upsampler(nn.Module):
    """conv3x3 to 4x channels, then 2x DCR depth-to-space: (B, C, H, W) -> (B, C, 2H, 2W)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = nn.Conv2d(channels, 4 * channels, 3, padding=1)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        return depth_to_space(self.conv1(x_BCHW), 2)


class Level(nn.Module):
    """One resolution level: `block` ResBlocks, then `downsample` (encoder) or `upsample` (decoder) if asked."""

    def __init__(self, in_channels: int, out_channels: int, num_res_blocks: int, resample: str = "none"):
        super().__init__()
        self.block = nn.ModuleList(
            [ResBlock(in_channels if j == 0 else out_channels, out_channels) for j in range(num_res_blocks)])
        if resample == "down":
            self.downsample = nn.Conv2d(out_channels, out_channels, 3, stride=2, padding=1)
        elif resample == "up":
            self.upsample = Upsampler(out_channels)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        for block in self.block:
            x_BCHW = block(x_BCHW)
        if hasattr(self, "downsample"):
            x_BCHW = self.downsample(x_BCHW)
        if hasattr(self, "upsample"):
            x_BCHW = self.upsample(x_BCHW)
        return x_BCHW


class Encoder(nn.Module):
    """(B, in_channels, H, W) in [-1, 1] -> continuous latents (B, z_channels, H / f, W / f), f = 2 ** (levels - 1)."""

    def __init__(self, config: VQConfig):
        super().__init__()
        widths = [config.base_channels * m for m in config.ch_mult]
        self.conv_in = nn.Conv2d(config.in_channels, config.base_channels, 3, padding=1, bias=False)
        self.down = nn.ModuleList()
        in_width = config.base_channels
        for i, width in enumerate(widths):
            resample = "down" if i < len(widths) - 1 else "none"
            self.down.append(Level(in_width, width, config.num_res_blocks, resample))
            in_width = width
        self.mid_block = nn.ModuleList([ResBlock(widths[-1], widths[-1]) for _ in range(config.num_res_blocks)])
        self.norm_out = group_norm(widths[-1])
        self.conv_out = nn.Conv2d(widths[-1], config.z_channels, 1)

    def forward(self, x_BCHW: torch.Tensor) -> torch.Tensor:
        x_BCHW = self.conv_in(x_BCHW)
        for level in self.down:
            x_BCHW = level(x_BCHW)
        for block in self.mid_block:
            x_BCHW = block(x_BCHW)
        return self.conv_out(F.silu(self.norm_out(x_BCHW)))


class Decoder(nn.Module):
    """Latents (B, z_channels, h, w) -> images (B, out_channels, h * f, w * f), roughly in [-1, 1]."""

    def __init__(self, config: VQConfig):
        super().__init__()
        widths = [config.base_channels * m for m in config.ch_mult]
        self.conv_in = nn.Conv2d(config.z_channels, widths[-1], 3, padding=1)
        self.mid_block = nn.ModuleList([ResBlock(widths[-1], widths[-1]) for _ in range(config.num_res_blocks)])
        # up[i] belongs to level i (same index as the encoder's down[i]) but they run from the last level to 0
        levels = [None] * len(widths)
        in_width = widths[-1]
        for i in reversed(range(len(widths))):
            levels[i] = Level(in_width, widths[i], config.num_res_blocks, "up" if i > 0 else "none")
            in_width = widths[i]
        self.up = nn.ModuleList(levels)
        self.norm_out = group_norm(widths[0])
        self.conv_out = nn.Conv2d(widths[0], config.out_channels, 3, padding=1)

    def forward(self, z_BCHW: torch.Tensor) -> torch.Tensor:
        x_BCHW = self.conv_in(z_BCHW)
        for block in self.mid_block:
            x_BCHW = block(x_BCHW)
        for level in reversed(self.up):
            x_BCHW = level(x_BCHW)
        return self.conv_out(F.silu(self.norm_out(x_BCHW)))
