"""The dynamics model's architecture (`GenieConfig`) and its training recipe (`TrainingRecipe`).

A config.json (the published GENIE_35M one, ours, or a `--genie_config` file) holds the fields of both: the
published file already mixes architecture with two training knobs (max_corrupt_rate, non_mlm_ratio).
`GenieConfig.from_dict` keeps the architecture and ignores the recipe's keys; `TrainingRecipe.from_dict` the other
way round; a key that belongs to neither is an error. config.json files written by earlier versions of this repo
load too (`_legacy`): the former share of whole-frame masking becomes the masking choice, and the keys of options
that were measured, dropped and deleted are accepted at their "off" values.
"""
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

from common.config import ConfigError, dataclass_from_dict, load_json
from common.errors import DataMismatchError

MASKING_SCHEMES = ("published", "whole_frames")


@dataclass
class GenieConfig:
    """Spatio-temporal MaskGIT dynamics model. Defaults are the published GENIE_35M config.

    Fields after the marked line are opt-in extensions: their defaults keep the published semantics, so published
    checkpoints load unchanged.
    """
    num_layers: int = 32
    num_heads: int = 8
    d_model: int = 256
    T: int = 16  # frames per window
    S: int = 256  # tokens per frame (H * W)
    image_vocab_size: int = 262144  # distinct image tokens; the mask token id is this value
    use_mup: bool = False

    num_factored_vocabs: int = 2
    factored_vocab_size: Optional[int] = None  # derived: image_vocab_size ** (1 / num_factored_vocabs)

    num_prompt_frames: int = 8  # ground-truth frames before the predicted ones (generation, delta-PSNR, masking)

    qkv_bias: bool = False
    proj_bias: bool = True
    attn_drop: float = 0.0
    qk_norm: bool = False

    mlp_ratio: float = 4.0
    mlp_drop: float = 0.0
    mlp_bias: bool = True

    # ---- opt-in extensions (defaults = published behaviour) ----
    # Action conditioning (genie/actions.py): frame t's tokens get + embed(real action of frame t-1) and
    # + embed(latent action of the transition t-1 -> t). No parameters are created while these are off.
    action_names: Optional[List[str]] = None  # real action streams actions/<name>.bin, concatenated in this order
    action_dim: int = 0  # total width of those streams (set by train.py from the data)
    action_mean: Optional[List[float]] = None  # per-dimension normalization (train.py: from the training split)
    action_std: Optional[List[float]] = None
    # Read each real action row as the mean over the data's `stride` frames of the step t -> t+1 (everything
    # commanded between two window frames) instead of the row of frame t alone; mean/std are of these means.
    action_step_mean: bool = False
    num_latent_actions: int = 0  # LAM codebook size; ids come from actions/latent_action.bin (0 = off)
    action_dropout: float = 0.1  # training: probability that a frame's action inputs are replaced by "no action"
    # Previous-frame pointer (genie/copy_head.py): each predicted token may copy a token of frame t-1 up to this
    # many positions away in each direction, mixed with the readout. None: off, no parameters.
    copy_radius: Optional[int] = None
    # With the pointer: each token's input also gets + embed(which of those neighbours in its previous frame hold the
    # same token), so the model sees how the scene moved at every position (motion evidence for the pointer).
    copy_match_input: bool = False
    # 2-D rotary positions in the spatial attention (genie/transformer.py): scores depend on the tokens' relative offset.
    spatial_rope: bool = False
    # Rotary positions in the temporal attention too (genie/transformer.py): half of each head's channels turned by the
    # frame index, so a query scores a key by how many frames back it lies, whatever its own frame.
    temporal_rope: bool = False

    def __post_init__(self):
        for name in ("num_layers", "num_heads", "d_model", "T", "S", "image_vocab_size", "num_factored_vocabs"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"GenieConfig.{name} must be positive, got {getattr(self, name)}")
        if self.d_model % self.num_heads:
            raise ConfigError(f"GenieConfig: d_model {self.d_model} is not divisible by num_heads {self.num_heads}")
        if math.isqrt(self.S) ** 2 != self.S:
            raise ConfigError(f"GenieConfig: S={self.S} is not a square number of tokens (H = W required)")
        root = round(self.image_vocab_size ** (1 / self.num_factored_vocabs))
        if root ** self.num_factored_vocabs != self.image_vocab_size:
            raise ConfigError(f"GenieConfig: image_vocab_size {self.image_vocab_size} is not a perfect "
                              f"{self.num_factored_vocabs}-th power")
        if self.factored_vocab_size is not None and self.factored_vocab_size != root:
            raise ConfigError(f"GenieConfig: factored_vocab_size {self.factored_vocab_size} != "
                              f"image_vocab_size ** (1/{self.num_factored_vocabs}) = {root}")
        self.factored_vocab_size = root
        if not 1 <= self.num_prompt_frames < self.T:
            raise ConfigError(f"GenieConfig: num_prompt_frames {self.num_prompt_frames} must be in [1, T={self.T})")
        self._check_actions()
        for name in ("spatial_rope", "temporal_rope"):
            if getattr(self, name) and (self.d_model // self.num_heads) % 4:
                raise ConfigError(f"GenieConfig: {name} needs a head width (d_model / num_heads = "
                                  f"{self.d_model // self.num_heads}) divisible by 4")
        if self.copy_radius is not None and not 0 <= self.copy_radius < self.H:
            raise ConfigError(f"GenieConfig: copy_radius must be None (off) or in [0, {self.H}), "
                              f"got {self.copy_radius}")
        if self.copy_match_input and self.copy_radius is None:
            raise ConfigError("GenieConfig: copy_match_input needs copy_radius (the neighbours it compares)")

    def _check_actions(self) -> None:
        names = self.action_names
        if names is not None:
            if not names or not all(isinstance(n, str) and n for n in names) or len(set(names)) != len(names):
                raise ConfigError(f"GenieConfig: action_names must be a non-empty list of distinct names, got {names}")
            if "latent_action" in names:
                raise ConfigError("GenieConfig: latent actions are ids, not real actions: use num_latent_actions")
        if self.action_dim < 0 or (self.action_dim > 0) != (names is not None):
            raise ConfigError(f"GenieConfig: action_dim {self.action_dim} must be > 0 exactly when action_names is "
                              f"set (action_names={names})")
        if names is not None and self.action_dim < len(names):
            raise ConfigError(f"GenieConfig: action_dim {self.action_dim} < {len(names)} action streams {names}")
        if (self.action_mean is None) != (self.action_std is None):
            raise ConfigError("GenieConfig: action_mean and action_std must be given together")
        if self.action_mean is not None:
            if len(self.action_mean) != self.action_dim or len(self.action_std) != self.action_dim:
                raise ConfigError(f"GenieConfig: action_mean / action_std need action_dim = {self.action_dim} "
                                  f"values, got {len(self.action_mean)} and {len(self.action_std)}")
            if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in self.action_mean + self.action_std) \
                    or min(self.action_std) <= 0:
                raise ConfigError("GenieConfig: action_mean must be finite and action_std finite and positive")
        if self.action_step_mean and names is None:
            raise ConfigError("GenieConfig: action_step_mean needs real action streams (action_names)")
        if self.num_latent_actions < 0:
            raise ConfigError(f"GenieConfig: num_latent_actions must be >= 0, got {self.num_latent_actions}")
        if not 0.0 <= self.action_dropout <= 1.0:
            raise ConfigError(f"GenieConfig: action_dropout must be in [0, 1], got {self.action_dropout}")

    @property
    def H(self) -> int:
        return math.isqrt(self.S)

    @property
    def W(self) -> int:
        return math.isqrt(self.S)

    @property
    def mask_token_id(self) -> int:
        return self.image_vocab_size

    @property
    def uses_actions(self) -> bool:
        """Whether the model takes real or latent action inputs."""
        return self.action_dim > 0 or self.num_latent_actions > 0

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "GenieConfig") -> "GenieConfig":
        """The architecture fields of a config dict; the training recipe's keys are left to TrainingRecipe."""
        return dataclass_from_dict(cls, _split(d, source)[0], source)

    @classmethod
    def from_pretrained(cls, json_path) -> "GenieConfig":
        """Load a config JSON file (the name the 1X code uses)."""
        return cls.from_dict(load_json(json_path, "GENIE config"), source=str(json_path))


@dataclass
class TrainingRecipe:
    """How the dynamics model is trained (training/masking.py, the loss in genie/model.py). Defaults are the published
    recipe; nothing here changes the network or its inference."""
    # which tokens a training example hides (training/masking.py):
    # "published": the published MaskGIT corruption and masking (partly masked frames from a random first one on);
    # "whole_frames": every 2nd or 3rd frame masked whole, as the challenge evaluates: each masked frame predicted
    # from whole earlier frames, nothing of itself revealed (every shipped sample-world recipe)
    masking: str = "published"
    # random factor values at up to this rate in every window (both schemes)
    max_corrupt_rate: float = 0.2
    # "published" only: this share of the batches corrupted more in later frames (closer to autoregressive inference)
    non_mlm_ratio: float = 0.5
    # this share of the examples has part of its masked tokens filled with the model's own guesses, as MaskGIT's
    # later steps see them at inference, so the model learns how far to trust them
    self_reveal_ratio: float = 0.0
    # this share of the windows is played backward in time, each pair of real action columns in time_reverse_swaps
    # swapped: a first-person walk played backward is the opposite walk (forward <-> backward, left <-> right turns),
    # so a command the walks hold rarely also learns from its mirror. A window in which any other column is nonzero
    # (e.g. USE: a door opened and played backward closes) is never reversed (training/masking.py)
    time_reverse_ratio: float = 0.0
    time_reverse_swaps: Optional[List[List[int]]] = None

    def __post_init__(self):
        if self.masking not in MASKING_SCHEMES:
            raise ConfigError(f"TrainingRecipe: masking must be one of {MASKING_SCHEMES}, got {self.masking!r}")
        for name in ("max_corrupt_rate", "non_mlm_ratio", "self_reveal_ratio", "time_reverse_ratio"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ConfigError(f"TrainingRecipe: {name} must be in [0, 1], got {value}")
        swaps = self.time_reverse_swaps or []
        flat = [i for pair in swaps if isinstance(pair, (list, tuple)) for i in pair]
        if (any(not isinstance(pair, (list, tuple)) or len(pair) != 2 for pair in swaps)
                or any(not isinstance(i, int) or isinstance(i, bool) or i < 0 for i in flat)
                or len(set(flat)) != len(flat)):
            raise ConfigError(f"TrainingRecipe: time_reverse_swaps must be pairs of distinct action column indices "
                              f"(each index at most once), e.g. [[0, 1], [2, 3]], got {self.time_reverse_swaps}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "TrainingRecipe") -> "TrainingRecipe":
        """The recipe fields of a config dict (architecture keys are left to GenieConfig)."""
        return dataclass_from_dict(cls, _split(d, source)[1], source)

    @classmethod
    def from_pretrained(cls, json_path) -> "TrainingRecipe":
        return cls.from_dict(load_json(json_path, "GENIE config"), source=str(json_path))


# config.json keys of earlier versions: the share of whole-frame masking (named teacher_forced_ratio before that)
LEGACY_MASKING_KEYS = ("whole_frame_mask_ratio", "teacher_forced_ratio")
# options measured, dropped and deleted (docs/experiments.md, "Removed options"; their code is in git history up to
# commit 307ac4a): each key loads at its value that turned the option off, and any other value is an error
REMOVED_KEYS = {"two_stream_ratio": 0.0, "two_stream_partial_ratio": 0.0, "own_context_ratio": 0.0,
                "guess_temperature": 0.0, "clean_prefix_ratio": 0.0, "context_noise_ratio": 0.0,
                "context_noise_max": 0.0, "bit_loss_weight": 0.0, "speed_jitter": 0.0, "speed_jitter_columns": None,
                "context_noise_input": False, "mlp_activation": "gelu"}


def _legacy(d: dict, source: str) -> dict:
    """A config dict of any version -> one with today's keys (see the module doc)."""
    d = dict(d)
    for key, off in REMOVED_KEYS.items():
        if key in d and d.pop(key) != off:
            raise ConfigError(f"{source}: {key} was a dropped experiment and has been removed (its last code is in "
                              f"git commit 307ac4a, its numbers in docs/experiments.md); only {off!r} loads")
    for key in LEGACY_MASKING_KEYS:
        if key in d:
            share = d.pop(key)
            if share not in (0, 1) or "masking" in d:
                raise ConfigError(f"{source}: {key} {share!r} is no longer supported: set \"masking\" to "
                                  f"\"published\" (was 0) or \"whole_frames\" (was 1)")
            d["masking"] = "whole_frames" if share == 1 else "published"
    return d


def _split(d: dict, source: str):
    """A config dict -> (architecture dict, recipe dict); unknown keys are errors naming both dataclasses."""
    if not isinstance(d, dict):
        raise ConfigError(f"{source}: expected a JSON object, got {type(d).__name__}")
    d = _legacy(d, source)
    model_keys = {f.name for f in dataclasses.fields(GenieConfig)}
    recipe_keys = {f.name for f in dataclasses.fields(TrainingRecipe)}
    unknown = sorted(set(d) - model_keys - recipe_keys)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {unknown}; known keys: GenieConfig {sorted(model_keys)}, "
                          f"TrainingRecipe {sorted(recipe_keys)}")
    return {k: v for k, v in d.items() if k in model_keys}, {k: v for k, v in d.items() if k in recipe_keys}


def save_config(json_path, config: GenieConfig, recipe: Optional[TrainingRecipe] = None) -> None:
    """Write config.json: the architecture, plus the recipe it was trained with when known (as published)."""
    d = {**config.to_dict(), **(recipe.to_dict() if recipe is not None else {})}
    Path(json_path).write_text(json.dumps(d, indent=2, sort_keys=True) + "\n")


def check_dataset_matches(config: GenieConfig, dataset, window_size: int, source: str,
                          exact_window: bool = True) -> None:
    """Raise DataMismatchError, naming the dataset's metadata.json and `source` (the model config file or checkpoint
    the config came from), when a model of `config` cannot read `dataset`'s windows of `window_size` frames.

    exact_window: training and generation need window_size == T; evaluation also accepts shorter windows.
    """
    meta, where = dataset.metadata, dataset.data_dir / "metadata.json"
    if exact_window and window_size != config.T:
        raise DataMismatchError(f"--window_size {window_size} must equal the model's T={config.T} ({source})")
    if window_size > config.T:
        raise DataMismatchError(f"--window_size {window_size} is longer than the model's T={config.T} frames "
                                f"({source})")
    side = meta["s"]
    if side ** 2 != config.S:
        raise DataMismatchError(f"{where}: frames are {side}x{side} = {side ** 2} tokens per frame but the model has "
                                f"S={config.S} ({source}); use a model with S={side ** 2}")
    if meta["vocab_size"] != config.image_vocab_size:
        raise DataMismatchError(f"{where}: vocab_size {meta['vocab_size']} differs from the model's image_vocab_size "
                                f"{config.image_vocab_size} ({source}): they come from different tokenizers")
