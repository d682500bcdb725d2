"""VQConfig: the MAGVIT2 tokenizer's architecture and loss weights. Defaults are the 1X `magvit2.ckpt` tokenizer."""
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import List

from common.config import ConfigError, dataclass_from_dict, load_json


@dataclass
class VQConfig:
    """Encoder/decoder shape (docs/formats.md §4) and the training loss weights.

    256x256 RGB in [-1, 1] <-> 16x16 latents of `z_channels` channels, each quantized to +-1 (LFQ), so a token id
    has `z_channels` bits and `codebook_size` = 2 ** z_channels.
    """
    in_channels: int = 3
    z_channels: int = 18
    out_channels: int = 3
    base_channels: int = 128  # width of level 0; level i has base_channels * ch_mult[i]
    ch_mult: List[int] = field(default_factory=lambda: [1, 1, 2, 2, 4])
    num_res_blocks: int = 2
    codebook_size: int = 2 ** 18
    resolution: int = 256  # training / default image side; any side divisible by `downsample_factor` works

    # loss weights (magvit2/losses.py, magvit2/train.py)
    l1_weight: float = 1.0
    perceptual_weight: float = 1.0
    commitment_weight: float = 0.25
    entropy_weight: float = 0.1
    entropy_temperature: float = 0.01
    disc_weight: float = 0.8
    gen_loss_weight: float = 0.1
    lecam_weight: float = 0.001
    disc_start: int = 0  # generator step at which the GAN losses switch on

    def __post_init__(self):
        self.ch_mult = list(self.ch_mult)
        for name in ("in_channels", "z_channels", "out_channels", "base_channels", "num_res_blocks", "resolution"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) <= 0:
                raise ConfigError(f"VQConfig.{name} must be a positive int, got {getattr(self, name)!r}")
        if not self.ch_mult or any(not isinstance(m, int) or m <= 0 for m in self.ch_mult):
            raise ConfigError(f"VQConfig.ch_mult must be a non-empty list of positive ints, got {self.ch_mult!r}")
        # compared by bits: 2 ** z_channels of a corrupted, huge z_channels would never finish computing
        size = self.codebook_size
        if not isinstance(size, int) or size <= 0 or size & (size - 1) or size.bit_length() - 1 != self.z_channels:
            raise ConfigError(f"VQConfig: codebook_size {size!r} != 2 ** z_channels (z_channels = "
                              f"{self.z_channels}); lookup-free quantization has one bit per latent channel")
        bad_widths = [self.base_channels * m for m in self.ch_mult if (self.base_channels * m) % 32]
        if bad_widths:
            raise ConfigError(f"VQConfig: every level width base_channels * ch_mult[i] must be divisible by 32 "
                              f"(GroupNorm with 32 groups); got widths {bad_widths}")
        if self.resolution % self.downsample_factor:
            raise ConfigError(f"VQConfig: resolution {self.resolution} is not divisible by the downsample factor "
                              f"{self.downsample_factor} = 2 ** (len(ch_mult) - 1)")
        if self.entropy_temperature <= 0:
            raise ConfigError(f"VQConfig.entropy_temperature must be > 0, got {self.entropy_temperature}")

    @property
    def num_levels(self) -> int:
        return len(self.ch_mult)

    @property
    def downsample_factor(self) -> int:
        return 2 ** (len(self.ch_mult) - 1)

    def latent_size(self, image_size: int = None) -> int:
        """Side of the latent / token grid for a square image of side `image_size` (default `resolution`)."""
        image_size = self.resolution if image_size is None else image_size
        if image_size % self.downsample_factor:
            raise ValueError(f"image side {image_size} is not divisible by the tokenizer's downsample factor "
                             f"{self.downsample_factor}")
        return image_size // self.downsample_factor

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "VQConfig") -> "VQConfig":
        return dataclass_from_dict(cls, d, source)

    def save(self, json_path) -> None:
        Path(json_path).write_text(json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n")

    @classmethod
    def from_pretrained(cls, json_path) -> "VQConfig":
        """Load a VQConfig JSON file."""
        return cls.from_dict(load_json(json_path, "tokenizer config"), source=str(json_path))
