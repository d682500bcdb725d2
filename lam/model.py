"""Latent action model (LAM, Genie section 2.1): a discrete action between two frames, learned from video alone.

    past frames + next frame --ActionEncoder--> z (B, D) --VectorQuantizer--> one of K codes (K = 8 by default)
    past frames + code       --FrameDecoder---> predicted next frame, in pixels

The decoder sees the next frame only through the K-way bottleneck, so to reconstruct it the codes must carry what
changed between the frames that the past cannot predict: the action. At inference only the codebook is used: the
dynamics model takes code ids (`infer_actions` labels a video, `decode_with_actions` shows what a code does).

Small-compute choices that make the codes track camera motion: a cost volume in the encoder (sees large shifts), a
flow warp in the decoder (makes motion cheap to express) and an extra loss on average-pooled frames (at 64 px,
unpredictable texture outweighs where the view moved). On a small sample-world subset (700 steps) the codes
explained ~2-3% of the heading change without the cost volume and the pooled loss, ~17% with both. Euclidean VQ
with data-initialised codes and dead-code restarts keeps all codes in use.

Frames are float tensors in [-1, 1], channels first. `past` holds `num_past_frames` frames spaced `stride` raw
frames apart, oldest first; `next` is the frame `stride` raw frames after the last past frame.
"""
import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import torch
import torch.nn as nn
import torch.nn.functional as F
from einops import rearrange
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from common.config import ConfigError, dataclass_from_dict, load_json
from common.errors import CheckpointError
from common.files import atomic_file
from common.integrity import update_manifest, verify_manifest

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"


@dataclass
class LAMConfig:
    image_size: int = 64  # frames are image_size x image_size
    image_channels: int = 3
    num_past_frames: int = 1  # context frames before the target frame
    stride: int = 15  # raw frames between the frames the LAM compares; recorded so that labelers use the same gap
    channels: list[int] = field(default_factory=lambda: [16, 32, 64])  # conv widths; each level halves the size
    num_attention_blocks: int = 1  # self-attention blocks at the bottleneck of encoder and decoder (global motion)
    num_heads: int = 4
    corr_radius: int = 3  # encoder cost volume reach, in bottleneck cells (8 px each at 64 px, 3 levels); 0: off
    predict_flow: bool = True  # the decoder warps the last past frame by a predicted flow before adding a residual
    latent_dim: int = 32  # width of the continuous action vector and of the codes
    codebook_size: int = 8
    l2_normalize_codes: bool = False  # cosine codebook; euclidean (default) kept codes apart better in tests
    codebook_weight: float = 1.0  # pulls codes towards the encoder outputs assigned to them
    commitment_weight: float = 0.25  # pulls encoder outputs towards their codes
    recon_weight: float = 1.0  # pixel MSE of the predicted next frame
    # Extra MSE between the predicted and true next frame average-pooled by lowres_pool (0: off). At full
    # resolution, texture detail nobody can predict drowns where the view moved; at low resolution, camera motion
    # is most of the change, so this weight steers the codes towards motion, i.e. towards actions.
    lowres_pool: int = 8
    lowres_weight: float = 4.0
    dead_code_steps: int = 50  # a code no training batch used for this many steps is restarted; 0 disables

    def __post_init__(self):
        for name in ("image_size", "image_channels", "num_past_frames", "stride", "num_heads", "latent_dim",
                     "codebook_size"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"LAMConfig.{name} must be positive, got {getattr(self, name)}")
        if self.codebook_size < 2:
            raise ConfigError(f"LAMConfig.codebook_size must be at least 2, got {self.codebook_size}")
        if not self.channels or any(not isinstance(c, int) or c <= 0 for c in self.channels):
            raise ConfigError(f"LAMConfig.channels must be a non-empty list of positive ints, got {self.channels}")
        if self.image_size % self.downsample_factor:
            raise ConfigError(f"LAMConfig: image_size {self.image_size} is not divisible by 2 ** len(channels) = "
                              f"{self.downsample_factor}")
        if self.channels[-1] % self.num_heads:
            raise ConfigError(f"LAMConfig: channels[-1] = {self.channels[-1]} is not divisible by num_heads "
                              f"{self.num_heads}")
        if self.corr_radius < 0:
            raise ConfigError(f"LAMConfig.corr_radius must be >= 0, got {self.corr_radius}")
        if self.num_attention_blocks < 0:
            raise ConfigError(f"LAMConfig.num_attention_blocks must be >= 0, got {self.num_attention_blocks}")
        if self.lowres_pool < 0 or (self.lowres_pool and self.image_size % self.lowres_pool):
            raise ConfigError(f"LAMConfig.lowres_pool must be 0 or divide image_size {self.image_size}, "
                              f"got {self.lowres_pool}")
        if self.dead_code_steps < 0:
            raise ConfigError(f"LAMConfig.dead_code_steps must be >= 0, got {self.dead_code_steps}")

    @property
    def downsample_factor(self) -> int:
        return 2 ** len(self.channels)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "LAMConfig") -> "LAMConfig":
        return dataclass_from_dict(cls, d, source)


def _norm(channels: int) -> nn.GroupNorm:
    return nn.GroupNorm(math.gcd(8, channels), channels)


class FiLM(nn.Module):
    """Scales and shifts a feature map by an action vector.

    Applied right after a normalization: before one, the norm would undo a per-channel scale and shift. Randomly
    initialised (not zero): the action must matter from the first step, or the encoder gets no reconstruction
    gradient and the commitment loss alone collapses all actions onto one code.
    """

    def __init__(self, action_dim: int, channels: int):
        super().__init__()
        self.proj = nn.Linear(action_dim, 2 * channels)

    def forward(self, x_BCHW: torch.Tensor, action_BD: torch.Tensor) -> torch.Tensor:
        scale_BC, shift_BC = self.proj(action_BD).chunk(2, dim=-1)
        return x_BCHW * (1 + scale_BC[:, :, None, None]) + shift_BC[:, :, None, None]


class ResBlock(nn.Module):
    """Pre-norm residual block of two 3x3 convs; with action_dim, both norms are followed by an action FiLM."""

    def __init__(self, channels: int, action_dim: Optional[int] = None):
        super().__init__()
        self.norm1 = _norm(channels)
        self.conv1 = nn.Conv2d(channels, channels, 3, padding=1)
        self.norm2 = _norm(channels)
        self.conv2 = nn.Conv2d(channels, channels, 3, padding=1)
        self.film1 = FiLM(action_dim, channels) if action_dim else None
        self.film2 = FiLM(action_dim, channels) if action_dim else None

    def forward(self, x_BCHW: torch.Tensor, action_BD: Optional[torch.Tensor] = None) -> torch.Tensor:
        h = self.norm1(x_BCHW)
        if self.film1 is not None:
            h = self.film1(h, action_BD)
        h = self.norm2(self.conv1(F.silu(h)))
        if self.film2 is not None:
            h = self.film2(h, action_BD)
        return x_BCHW + self.conv2(F.silu(h))


class ConvEncoder(nn.Module):
    """(B, C_in, H, W) -> one feature map per level: level i has channels[i] channels at H / 2^(i+1)."""

    def __init__(self, in_channels: int, channels: list[int]):
        super().__init__()
        self.stem = nn.Conv2d(in_channels, channels[0], 4, stride=2, padding=1)
        self.blocks = nn.ModuleList(ResBlock(c) for c in channels)
        self.downs = nn.ModuleList(nn.Conv2d(a, b, 4, stride=2, padding=1) for a, b in zip(channels, channels[1:]))

    def forward(self, x_BCHW: torch.Tensor) -> list[torch.Tensor]:
        h = self.stem(x_BCHW)
        features = []
        for i, block in enumerate(self.blocks):
            if i > 0:
                h = self.downs[i - 1](F.silu(h))
            h = block(h)
            features.append(h)
        return features


class AttentionBlock(nn.Module):
    """Self-attention + MLP over the positions of a small feature map, so that any position can draw on any other:
    a camera turn moves content across most of the frame, beyond the reach of a few 3x3 convs. With action_dim,
    both norms are followed by an action FiLM (the action picks where content comes from)."""

    def __init__(self, channels: int, side: int, num_heads: int, action_dim: Optional[int] = None):
        super().__init__()
        self.num_heads = num_heads
        self.pos_CHW = nn.Parameter(torch.randn(channels, side, side) * 0.02)
        self.norm1 = _norm(channels)
        self.qkv = nn.Linear(channels, 3 * channels)
        self.proj = nn.Linear(channels, channels)
        self.norm2 = _norm(channels)
        self.mlp = nn.Sequential(nn.Linear(channels, 4 * channels), nn.GELU(), nn.Linear(4 * channels, channels))
        self.film1 = FiLM(action_dim, channels) if action_dim else None
        self.film2 = FiLM(action_dim, channels) if action_dim else None

    def _modulate(self, norm: nn.Module, film: Optional[FiLM], x_BCHW: torch.Tensor, action_BD) -> torch.Tensor:
        h = norm(x_BCHW)
        return rearrange(film(h, action_BD) if film is not None else h, "b c h w -> b (h w) c")

    def forward(self, x_BCHW: torch.Tensor, action_BD: Optional[torch.Tensor] = None) -> torch.Tensor:
        height = x_BCHW.shape[2]
        x_BCHW = x_BCHW + self.pos_CHW
        q, k, v = rearrange(self.qkv(self._modulate(self.norm1, self.film1, x_BCHW, action_BD)),
                            "b s (three n d) -> three b n s d", three=3, n=self.num_heads)
        attn_BSC = rearrange(F.scaled_dot_product_attention(q, k, v), "b n s d -> b s (n d)")
        x_BCHW = x_BCHW + rearrange(self.proj(attn_BSC), "b (h w) c -> b c h w", h=height)
        mlp_BSC = self.mlp(self._modulate(self.norm2, self.film2, x_BCHW, action_BD))
        return x_BCHW + rearrange(mlp_BSC, "b (h w) c -> b c h w", h=height)


def local_correlation(a_BCHW: torch.Tensor, b_BCHW: torch.Tensor, radius: int) -> torch.Tensor:
    """Cosine similarity of each position of a with the positions of b within +-radius cells (a cost volume, as in
    optical flow networks): (B, (2 radius + 1)^2, H, W), displacement (dy, dx) in row-major order."""
    a_BCHW, b_BCHW = F.normalize(a_BCHW, dim=1), F.normalize(b_BCHW, dim=1)
    height, width = a_BCHW.shape[2:]
    b_padded = F.pad(b_BCHW, (radius, radius, radius, radius))
    return torch.stack([(a_BCHW * b_padded[:, :, dy: dy + height, dx: dx + width]).sum(dim=1)
                        for dy in range(2 * radius + 1) for dx in range(2 * radius + 1)], dim=1)


class ActionEncoder(nn.Module):
    """Past frames and next frame -> continuous action vector (B, latent_dim).

    Two views of the transition meet at the bottleneck: convs over the frames stacked on channels (with the change
    from the last past frame), and a cost volume between per-frame features of the last past frame and the next
    frame, which shows how far the content moved even when that is many pixels.
    """

    def __init__(self, cfg: LAMConfig):
        super().__init__()
        self.corr_radius = cfg.corr_radius
        in_channels = (cfg.num_past_frames + 2) * cfg.image_channels
        self.convs = ConvEncoder(in_channels, cfg.channels)
        if cfg.corr_radius:
            self.frame_convs = ConvEncoder(cfg.image_channels, cfg.channels)
            self.corr_proj = nn.Conv2d((2 * cfg.corr_radius + 1) ** 2, cfg.channels[-1], 1)
        side = cfg.image_size // cfg.downsample_factor
        self.attention = nn.ModuleList(AttentionBlock(cfg.channels[-1], side, cfg.num_heads)
                                       for _ in range(cfg.num_attention_blocks))
        self.head = nn.Linear(cfg.channels[-1] * side * side, cfg.latent_dim)

    def forward(self, past_BPCHW: torch.Tensor, next_BCHW: torch.Tensor) -> torch.Tensor:
        x_BCHW = torch.cat([rearrange(past_BPCHW, "b p c h w -> b (p c) h w"), next_BCHW,
                            next_BCHW - past_BPCHW[:, -1]], dim=1)
        h_BCHW = self.convs(x_BCHW)[-1]
        if self.corr_radius:
            pair_BCHW = torch.cat([past_BPCHW[:, -1], next_BCHW])
            last_BCHW, next_features_BCHW = self.frame_convs(pair_BCHW)[-1].chunk(2)
            h_BCHW = h_BCHW + self.corr_proj(local_correlation(last_BCHW, next_features_BCHW, self.corr_radius))
        for block in self.attention:
            h_BCHW = block(h_BCHW)
        return self.head(F.silu(h_BCHW).flatten(1))


class FrameDecoder(nn.Module):
    """Past frames + action vector -> next frame (B, C, H, W), predicted as a change of the last past frame.

    A U-Net over the past frames only, with attention at the bottleneck; the action enters by FiLM in every decoder
    block and before the output. With predict_flow, the output is the last past frame warped by a predicted flow
    field plus a residual: camera motion, the typical action, then costs the decoder a smooth flow instead of
    re-synthesising every moved pixel, so the code has a cheap way to pay off.
    """

    def __init__(self, cfg: LAMConfig):
        super().__init__()
        chans = cfg.channels
        self.convs = ConvEncoder(cfg.num_past_frames * cfg.image_channels, chans)
        side = cfg.image_size // cfg.downsample_factor
        self.attention = nn.ModuleList(AttentionBlock(chans[-1], side, cfg.num_heads, cfg.latent_dim)
                                       for _ in range(cfg.num_attention_blocks))
        self.blocks = nn.ModuleList(ResBlock(c, cfg.latent_dim) for c in chans)
        self.ups = nn.ModuleList(nn.ConvTranspose2d(b, a, 4, stride=2, padding=1) for a, b in zip(chans, chans[1:]))
        self.out_norm = _norm(chans[0])
        self.out_film = FiLM(cfg.latent_dim, chans[0])
        self.out = nn.ConvTranspose2d(chans[0], cfg.image_channels, 4, stride=2, padding=1)
        self.flow = nn.ConvTranspose2d(chans[0], 2, 4, stride=2, padding=1) if cfg.predict_flow else None
        if self.flow is not None:  # start from the identity warp
            nn.init.zeros_(self.flow.weight)
            nn.init.zeros_(self.flow.bias)

    def _warp(self, frame_BCHW: torch.Tensor, flow_B2HW: torch.Tensor) -> torch.Tensor:
        """Sample frame at (identity grid + flow); flow in grid_sample's [-1, 1] units, (x, y) channels."""
        identity_B23 = torch.eye(2, 3, device=frame_BCHW.device, dtype=frame_BCHW.dtype).expand(len(frame_BCHW), 2, 3)
        grid_BHW2 = F.affine_grid(identity_B23, list(frame_BCHW.shape), align_corners=False)
        grid_BHW2 = grid_BHW2 + rearrange(flow_B2HW, "b two h w -> b h w two")
        return F.grid_sample(frame_BCHW, grid_BHW2, padding_mode="border", align_corners=False)

    def forward(self, past_BPCHW: torch.Tensor, action_BD: torch.Tensor) -> torch.Tensor:
        skips = self.convs(rearrange(past_BPCHW, "b p c h w -> b (p c) h w"))
        h = skips[-1]
        for block in self.attention:
            h = block(h, action_BD)
        for i in reversed(range(len(skips))):
            if i < len(skips) - 1:
                h = self.ups[i](F.silu(h)) + skips[i]
            h = self.blocks[i](h, action_BD)
        h = F.silu(self.out_film(self.out_norm(h), action_BD))
        base_BCHW = past_BPCHW[:, -1]
        if self.flow is not None:
            base_BCHW = self._warp(base_BCHW, self.flow(h).to(base_BCHW.dtype))
        return base_BCHW + self.out(h)


@dataclass
class VQOutput:
    z_q: torch.Tensor  # (B, D) quantized vectors, straight-through: the forward value of the code, gradient to z
    ids: torch.Tensor  # (B,) int64 code ids
    loss: torch.Tensor  # scalar: codebook + commitment loss
    perplexity: torch.Tensor  # scalar: exp(entropy of the batch's code histogram); K when all codes equally used
    used_fraction: torch.Tensor  # scalar: fraction of the K codes used by this batch
    num_restarted: int  # dead codes re-initialised before this batch was quantized


def code_usage(ids: torch.Tensor, codebook_size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(perplexity, fraction of codes used) of a set of code ids."""
    counts = torch.bincount(ids.flatten(), minlength=codebook_size).float()
    probs = counts / counts.sum().clamp_min(1)
    entropy = -(probs * probs.clamp_min(1e-12).log()).sum()
    return entropy.exp(), (counts > 0).float().mean()


class VectorQuantizer(nn.Module):
    """Nearest-code quantizer with a straight-through gradient, codebook + commitment losses and dead-code restart.

    Restart: in training mode, each call counts for every code the calls since a batch last used it; a code unused
    for `dead_code_steps` calls is re-initialised, before the batch is quantized, to one of the batch's encoder
    outputs (the most recent ones there are), so it immediately wins those vectors and gets gradient again.
    """

    def __init__(self, codebook_size: int, dim: int, l2_normalize: bool = False, codebook_weight: float = 1.0,
                 commitment_weight: float = 0.25, dead_code_steps: int = 50):
        super().__init__()
        self.codebook_size = codebook_size
        self.l2_normalize = l2_normalize
        self.codebook_weight = codebook_weight
        self.commitment_weight = commitment_weight
        self.dead_code_steps = dead_code_steps
        self.codebook = nn.Parameter(torch.randn(codebook_size, dim))
        # Training bookkeeping, not model state: left out of checkpoints.
        self.register_buffer("steps_since_used", torch.zeros(codebook_size, dtype=torch.long), persistent=False)
        # Before the first training batch every code counts as dead, so that batch's encoder outputs initialise
        # the codebook (data-dependent init: random codes far from all encoder outputs would never be chosen).
        self.steps_since_used.fill_(max(dead_code_steps, 1) if dead_code_steps > 0 else 0)
        # A loaded codebook is trained: it must not be re-initialised by the next training batch.
        self.register_load_state_dict_post_hook(VectorQuantizer._mark_codes_used)

    @staticmethod
    def _mark_codes_used(module: "VectorQuantizer", incompatible_keys) -> None:
        module.steps_since_used.zero_()

    def _codes(self) -> torch.Tensor:
        """(K, D) the codes as the decoder receives them (unit length when l2_normalize), float32."""
        codes_KD = self.codebook.float()
        return F.normalize(codes_KD, dim=-1) if self.l2_normalize else codes_KD

    def _prepare(self, z_BD: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        z_BD = z_BD.float()
        return (F.normalize(z_BD, dim=-1) if self.l2_normalize else z_BD), self._codes()

    def nearest(self, z_BD: torch.Tensor) -> torch.Tensor:
        """(B, D) -> (B,) id of the closest code (cosine similarity when l2_normalize, else euclidean)."""
        z_BD, codes_KD = self._prepare(z_BD)
        return torch.cdist(z_BD, codes_KD).argmin(dim=-1)

    def lookup(self, ids: torch.Tensor) -> torch.Tensor:
        """(B,) ids -> (B, D) code vectors (normalized when l2_normalize), as the decoder receives them."""
        if ids.dtype not in (torch.int32, torch.int64):
            raise TypeError(f"latent action ids must be integers, got {ids.dtype}")
        if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= self.codebook_size):
            raise ValueError(f"latent action ids must be in [0, {self.codebook_size}), got "
                             f"[{int(ids.min())}, {int(ids.max())}]")
        return self._codes()[ids]

    @torch.no_grad()
    def _restart_dead_codes(self, z_BD: torch.Tensor) -> int:
        dead_K = self.steps_since_used >= self.dead_code_steps
        num_dead = int(dead_K.sum())
        if num_dead == 0:
            return 0
        # Distinct batch vectors where the batch has enough; repeats otherwise (the duplicates restart again later).
        pick = torch.randperm(len(z_BD), device=z_BD.device)[:num_dead]
        pick = pick[torch.arange(num_dead, device=z_BD.device) % len(pick)]
        self.codebook[dead_K] = z_BD[pick].to(self.codebook.dtype)
        self.steps_since_used[dead_K] = 0
        return num_dead

    def forward(self, z_BD: torch.Tensor) -> VQOutput:
        num_restarted = 0
        if self.training and self.dead_code_steps > 0:
            num_restarted = self._restart_dead_codes(z_BD.detach())
        z_BD, codes_KD = self._prepare(z_BD)
        ids = torch.cdist(z_BD.detach(), codes_KD.detach()).argmin(dim=-1)
        q_BD = codes_KD[ids]
        loss = (self.codebook_weight * F.mse_loss(q_BD, z_BD.detach())
                + self.commitment_weight * F.mse_loss(z_BD, q_BD.detach()))
        z_q = z_BD + (q_BD - z_BD).detach()
        perplexity, used_fraction = code_usage(ids, self.codebook_size)
        if self.training:
            with torch.no_grad():
                self.steps_since_used += 1
                self.steps_since_used[torch.bincount(ids, minlength=self.codebook_size) > 0] = 0
        return VQOutput(z_q, ids, loss, perplexity, used_fraction, num_restarted)


@dataclass
class LAMOutput:
    loss: torch.Tensor  # scalar: recon_weight * recon_loss + lowres_weight * lowres_loss + vq_loss
    recon_loss: torch.Tensor  # scalar: pixel MSE of the predicted next frame ([-1, 1] scale)
    lowres_loss: torch.Tensor  # scalar: the same MSE after average pooling by lowres_pool (0 when off)
    vq_loss: torch.Tensor  # scalar
    recon: torch.Tensor  # (B, C, H, W) predicted next frame
    action_ids: torch.Tensor  # (B,) int64 latent action per transition
    z: torch.Tensor  # (B, latent_dim) continuous action vector before quantization
    perplexity: torch.Tensor  # scalar, over the batch
    used_fraction: torch.Tensor  # scalar, over the batch
    num_restarted: int


class LAM(nn.Module):
    def __init__(self, config: LAMConfig):
        super().__init__()
        self.config = config
        self.encoder = ActionEncoder(config)
        self.quantizer = VectorQuantizer(config.codebook_size, config.latent_dim, config.l2_normalize_codes,
                                         config.codebook_weight, config.commitment_weight, config.dead_code_steps)
        self.decoder = FrameDecoder(config)

    def _check_frames(self, past: torch.Tensor, next_frame: Optional[torch.Tensor] = None) -> None:
        cfg = self.config
        frame = (cfg.image_channels, cfg.image_size, cfg.image_size)
        if past.ndim != 5 or tuple(past.shape[1:]) != (cfg.num_past_frames, *frame):
            raise ValueError(f"past frames must have shape (B, {cfg.num_past_frames}, {', '.join(map(str, frame))}), "
                             f"got {tuple(past.shape)}")
        if next_frame is not None and tuple(next_frame.shape) != (past.shape[0], *frame):
            raise ValueError(f"next frame must have shape ({past.shape[0]}, {', '.join(map(str, frame))}), "
                             f"got {tuple(next_frame.shape)}")

    def forward(self, past_BPCHW: torch.Tensor, next_BCHW: torch.Tensor) -> LAMOutput:
        """past (B, P, C, H, W), next (B, C, H, W), both in [-1, 1] -> losses, reconstruction, action ids, stats."""
        self._check_frames(past_BPCHW, next_BCHW)
        z_BD = self.encoder(past_BPCHW, next_BCHW)
        vq = self.quantizer(z_BD)
        recon_BCHW = self.decoder(past_BPCHW, vq.z_q.to(z_BD.dtype))
        cfg = self.config
        recon_loss = F.mse_loss(recon_BCHW.float(), next_BCHW.float())
        lowres_loss = recon_loss.new_zeros(())
        if cfg.lowres_pool:
            lowres_loss = F.mse_loss(F.avg_pool2d(recon_BCHW.float(), cfg.lowres_pool),
                                     F.avg_pool2d(next_BCHW.float(), cfg.lowres_pool))
        loss = cfg.recon_weight * recon_loss + cfg.lowres_weight * lowres_loss + vq.loss
        return LAMOutput(loss, recon_loss, lowres_loss, vq.loss, recon_BCHW, vq.ids, z_BD, vq.perplexity,
                         vq.used_fraction, vq.num_restarted)

    @torch.no_grad()
    def encode(self, past_BPCHW: torch.Tensor, next_BCHW: torch.Tensor) -> torch.Tensor:
        """-> (B, latent_dim) continuous action vector before quantization."""
        self._check_frames(past_BPCHW, next_BCHW)
        return self.encoder(past_BPCHW, next_BCHW)

    @torch.no_grad()
    def infer_actions(self, past_BPCHW: torch.Tensor, next_BCHW: torch.Tensor) -> torch.Tensor:
        """-> (B,) int64 latent action id of each transition; never touches the dead-code bookkeeping."""
        return self.quantizer.nearest(self.encode(past_BPCHW, next_BCHW))

    @torch.no_grad()
    def decode_with_actions(self, past_BPCHW: torch.Tensor, action_ids: torch.Tensor) -> torch.Tensor:
        """past (B, P, C, H, W) + ids (B,) -> (B, C, H, W) predicted next frame (not clamped)."""
        self._check_frames(past_BPCHW)
        if action_ids.shape != (past_BPCHW.shape[0],):
            raise ValueError(f"action ids must have shape ({past_BPCHW.shape[0]},), got {tuple(action_ids.shape)}")
        action_BD = self.quantizer.lookup(action_ids.to(past_BPCHW.device))
        return self.decoder(past_BPCHW, action_BD.to(past_BPCHW.dtype))

    def save_pretrained(self, save_dir) -> None:
        """Write config.json + model.safetensors into save_dir, each atomically (temp file, then rename), and their
        digests into MANIFEST.json. A full disk raises WriteError and leaves the previous files in place."""
        save_dir = Path(save_dir)
        save_dir.mkdir(parents=True, exist_ok=True)
        state = {k: v.detach().contiguous().cpu() for k, v in self.state_dict().items()}
        atomic_file(save_dir / WEIGHTS_NAME, lambda tmp: save_file(state, str(tmp), metadata={"format": "pt"}),
                    "the LAM weights")
        text = json.dumps(self.config.to_dict(), indent=2, sort_keys=True) + "\n"
        atomic_file(save_dir / CONFIG_NAME, lambda tmp: tmp.write_text(text), "the LAM config")
        update_manifest(save_dir, (WEIGHTS_NAME, CONFIG_NAME))

    @classmethod
    def from_pretrained(cls, load_dir, device="cpu") -> "LAM":
        """Load a directory written by `save_pretrained`; errors name the file and what is wrong."""
        load_dir = Path(load_dir)
        if not load_dir.is_dir():
            raise FileNotFoundError(f"LAM checkpoint directory not found: {load_dir}")
        verify_manifest(load_dir, [WEIGHTS_NAME])  # IntegrityError (a CheckpointError) naming corrupt weights
        config = LAMConfig.from_dict(load_json(load_dir / CONFIG_NAME, "LAM config"), str(load_dir / CONFIG_NAME))
        weights_path = load_dir / WEIGHTS_NAME
        if not weights_path.is_file():
            raise FileNotFoundError(f"LAM weights file not found: {weights_path}")
        try:
            state = load_file(str(weights_path))
        except (SafetensorError, OSError) as e:
            raise CheckpointError(f"{weights_path}: not a readable safetensors file ({e})") from None
        model = cls(config)
        expected = model.state_dict()
        missing = sorted(set(expected) - set(state))
        unexpected = sorted(set(state) - set(expected))
        wrong = sorted(k for k in set(expected) & set(state) if expected[k].shape != state[k].shape)
        if missing or unexpected or wrong:
            raise CheckpointError(f"{weights_path} does not match {load_dir / CONFIG_NAME}: missing {missing[:5]}, "
                             f"unexpected {unexpected[:5]}, wrong shape {wrong[:5]}")
        model.load_state_dict(state)
        return model.to(device)


def frames_to_tensor(frames_NHWC) -> torch.Tensor:
    """uint8 frames (..., H, W, C) (numpy or torch) -> float (..., C, H, W) in [-1, 1]."""
    x = torch.as_tensor(frames_NHWC)
    return rearrange(x.float() / 127.5 - 1.0, "... h w c -> ... c h w")
