"""How frames are sampled from a dynamics model: `DecodingConfig`, kept with the weights as decoding.json.

A model trained here is meant to be sampled one way (the main command's: whole tokens at temperature 1, the copy
head's neighbours weighted e^2). That choice travels with the checkpoint, as a Hugging Face model's
generation_config.json does, so every command that samples the model decodes it the same way unless told
otherwise. A checkpoint without decoding.json (the published GENIE_35M / 138M, or one saved before this file
existed) decodes as the published code does: `DecodingConfig()`'s defaults.

The teacher-forced protocol scores the model as trained, as the challenge defines it: greedy, with no copy bias
(`DecodingConfig.teacher_forced`); only free-running futures use the temperature, copy bias, greedy tokens and stall
rule.
"""
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from common.config import ConfigError, dataclass_from_dict, load_json

DECODING_NAME = "decoding.json"
# which tokens each MaskGIT step reveals (genie.sampling.maskgit_sample): at random (the published way), or the most
# confident ones
UNMASK_MODES = ("random", "greedy")
# how greedy decoding (temperature 0) picks each token of a model with a copy head: choice -> what it does
GREEDY_TOKEN_CHOICES = {
    "joint": "the most probable whole token of the mixture",
    "best_neighbour": "as joint, but a copy takes the single most weighted neighbour's token, not the token with the "
                      "most weight summed over the neighbours holding it (which grows flat patches in rollouts)",
}


@dataclass(frozen=True)
class DecodingConfig:
    """The sampler's settings. Defaults are the published code's decoding.

    maskgit_steps: MaskGIT steps per frame. temperature: divides the logits; 0 is greedy (argmax). unmask_mode:
    which tokens each step reveals (UNMASK_MODES). copy_bias: models with a copy head only, added to
    every previous-frame neighbour's score (e^bias times its weight); 0 is the model as trained. greedy_tokens: how
    greedy decoding of a copy head's mixture picks a token (GREEDY_TOKEN_CHOICES). stall_ratio: free-running futures
    only, off when None: once a generated frame changes at most this share of what the prompt's frames change per
    step, every later frame repeats it (genie.inference.generate_frames).
    """
    maskgit_steps: int = 2
    temperature: float = 0.0
    unmask_mode: str = UNMASK_MODES[0]
    copy_bias: float = 0.0
    greedy_tokens: str = next(iter(GREEDY_TOKEN_CHOICES))
    stall_ratio: Optional[float] = None

    def __post_init__(self):
        if self.maskgit_steps < 1:
            raise ConfigError(f"decoding: maskgit_steps must be >= 1, got {self.maskgit_steps}")
        if not self.temperature >= 0:
            raise ConfigError(f"decoding: temperature must be >= 0, got {self.temperature}")
        if self.unmask_mode not in UNMASK_MODES:
            raise ConfigError(f"decoding: unmask_mode must be one of {UNMASK_MODES}, got {self.unmask_mode!r}")
        if self.greedy_tokens not in GREEDY_TOKEN_CHOICES:
            raise ConfigError(f"decoding: greedy_tokens must be one of {tuple(GREEDY_TOKEN_CHOICES)}, got "
                              f"{self.greedy_tokens!r}")
        if self.stall_ratio is not None and not 0.0 < self.stall_ratio <= 1.0:
            raise ConfigError(f"decoding: stall_ratio must be None (off) or in (0, 1], got {self.stall_ratio}")
        object.__setattr__(self, "temperature", float(self.temperature))
        object.__setattr__(self, "copy_bias", float(self.copy_bias))

    def override(self, **values) -> "DecodingConfig":
        """A copy with the given fields replaced; a value of None keeps this config's (an unset flag)."""
        return dataclasses.replace(self, **{k: v for k, v in values.items() if v is not None})

    def teacher_forced(self) -> "DecodingConfig":
        """The challenge's teacher-forced decoding of this model: its MaskGIT steps and unmasking, greedy, no copy
        bias, the mixture's most probable tokens."""
        return dataclasses.replace(self, temperature=0.0, copy_bias=0.0, greedy_tokens="joint", stall_ratio=None)

    def sampler_kwargs(self) -> dict:
        """The keyword arguments of genie.inference.generate_frames / teacher_forced (not the stall rule, which only
        free-running futures take)."""
        return dict(maskgit_steps=self.maskgit_steps, temperature=self.temperature, unmask_mode=self.unmask_mode)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "decoding") -> "DecodingConfig":
        return dataclass_from_dict(cls, d, source)


def load_decoding(checkpoint_dir) -> DecodingConfig:
    """The checkpoint's decoding.json, or the published decoding when it has none."""
    path = Path(checkpoint_dir) / DECODING_NAME
    if not path.is_file():
        return DecodingConfig()
    return DecodingConfig.from_dict(load_json(path, "decoding config"), source=str(path))


def save_decoding(json_path, decoding: DecodingConfig) -> None:
    Path(json_path).write_text(json.dumps(decoding.to_dict(), indent=2, sort_keys=True) + "\n")
