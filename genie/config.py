"""The dynamics model's architecture (`GenieConfig`) and its training recipe (`TrainingRecipe`).

A config.json (the published GENIE_35M one, ours, or a `--genie_config` file) holds the fields of both: the
published file already mixes architecture with two training knobs (max_corrupt_rate, non_mlm_ratio).
`GenieConfig.from_dict` keeps the architecture and ignores the recipe's keys; `TrainingRecipe.from_dict` the other
way round; a key that belongs to neither is an error. Checkpoints saved before the split (their config.json has
`teacher_forced_ratio`) load through `LEGACY_RECIPE_KEYS`.
"""
import dataclasses
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

from common.config import ConfigError, dataclass_from_dict, load_json
from common.errors import DataMismatchError

MLP_ACTIVATIONS = ("gelu", "relu2", "swiglu")


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
    # 2-D rotary positions in the spatial attention (genie/rope.py): scores depend on the tokens' relative offset.
    spatial_rope: bool = False
    # Rotary positions in the temporal attention too (genie/rope.py): half of each head's channels turned by the
    # frame index, so a query scores a key by how many frames back it lies, whatever its own frame.
    temporal_rope: bool = False
    # An input of how corrupted each context frame is (TrainingRecipe.context_noise_ratio): + level * a learned
    # vector on every token of the frame. Inference passes clean or generated frames at level 0, so it adds nothing.
    context_noise_input: bool = False
    # The MLP's nonlinearity (genie/transformer.py `Mlp`): "gelu" (published), "relu2" (ReLU squared, the same
    # parameters) or "swiglu" (a gated SiLU at 2/3 of the hidden width; fc1 twice as wide as its output).
    mlp_activation: str = "gelu"

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
        if self.mlp_activation not in MLP_ACTIVATIONS:
            raise ConfigError(f"GenieConfig: mlp_activation must be one of {MLP_ACTIVATIONS}, "
                              f"got {self.mlp_activation!r}")
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
    """How the dynamics model is trained: MaskGIT corruption and the opt-in objectives (genie/masking.py,
    genie/objectives.py). Defaults are the published recipe; nothing here changes the network or its inference."""
    # published MaskGIT corruption: random factor values at up to this rate, and this share of the batches
    # corrupted more in later frames (closer to autoregressive inference)
    max_corrupt_rate: float = 0.2
    non_mlm_ratio: float = 0.5
    # this share of the examples masks every 2nd or 3rd frame whole, as the challenge evaluates: each masked frame
    # is predicted from whole earlier frames, nothing of itself revealed
    whole_frame_mask_ratio: float = 0.0
    # of those examples, this share starts its masked frames anywhere in 1..num_prompt_frames instead of within the
    # first period, so that a target also follows a long run of clean frames, as a rollout's first generated frame
    # follows its prompt (without it no target follows more than 3)
    clean_prefix_ratio: float = 0.0
    # this share of the batches is two-stream: the clean window as context, every frame t >= 1 a target over
    # frames < t (the computation of the cached evaluation, with gradients)
    two_stream_ratio: float = 0.0
    # of the two-stream targets, this share is partly masked (MaskGIT's cosine rate) instead of whole
    two_stream_partial_ratio: float = 0.0
    # this share of the examples has part of its masked tokens filled with the model's own guesses, as MaskGIT's
    # later steps see them at inference, so the model learns how far to trust them
    self_reveal_ratio: float = 0.0
    # this share of the examples first has each fully masked frame filled with the model's own prediction,
    # and the frame after it becomes the target instead: predicted from a context whose last frame is the model's
    # guess, as every frame after the first is in a free-running rollout
    own_context_ratio: float = 0.0
    # the temperature of those guesses: 0 each factor's argmax (the greedy guesses these options began with); > 0
    # whole tokens drawn from the model's distribution (a copy head's mixture), as sampled rollouts reveal them
    guess_temperature: float = 0.0
    # this share of the examples has its unmasked frames 1.. corrupted (each token replaced by a random one with
    # probability level, level ~ U(0, context_noise_max) per frame), as a rollout's own frames are wrong in places;
    # with GenieConfig.context_noise_input the model is told each frame's level, so it learns how far to trust it
    context_noise_ratio: float = 0.0
    context_noise_max: float = 0.0
    # weight of a second loss beside the CE, in training only: for every bit of the predicted token's id, the binary
    # cross entropy of the probability the prediction puts on that bit's true value (genie/objectives.py, bit_loss).
    # Tokens a few bits apart decode to nearly the same pixels, and the expected number of wrong bits of a drawn
    # token is the sum of those probabilities' complements, which CE alone does not shape. Needs a power-of-two
    # factored vocabulary; 0: off (the CE alone)
    bit_loss_weight: float = 0.0
    # every training window's forward-speed inputs (the columns speed_jitter_columns of the concatenated real action
    # vector) scaled by one factor (1 + speed_jitter) ** U(-1, 1) drawn per window. How far a step forward moves the
    # view depends on how deep the room is, which the speed does not say; with the speed's magnitude unreliable the
    # model has to read the gain off the frames it has already seen (a new map's larger rooms move the view less
    # per step than the training maps'). 0: off
    speed_jitter: float = 0.0
    speed_jitter_columns: Optional[List[int]] = None

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, (int, float)) and not 0.0 <= value <= 1.0:
                raise ConfigError(f"TrainingRecipe: {f.name} must be in [0, 1], got {value}")
        if self.speed_jitter > 0 and not self.speed_jitter_columns:
            raise ConfigError("TrainingRecipe: speed_jitter needs speed_jitter_columns (the action columns to scale)")
        if any(c < 0 for c in self.speed_jitter_columns or []):
            raise ConfigError(f"TrainingRecipe: speed_jitter_columns must be column indices >= 0, got "
                              f"{self.speed_jitter_columns}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict, source: str = "TrainingRecipe") -> "TrainingRecipe":
        """The recipe fields of a config dict (architecture keys are left to GenieConfig)."""
        return dataclass_from_dict(cls, _split(d, source)[1], source)

    @classmethod
    def from_pretrained(cls, json_path) -> "TrainingRecipe":
        return cls.from_dict(load_json(json_path, "GENIE config"), source=str(json_path))


# config.json keys written by earlier versions of this repo -> their TrainingRecipe field
LEGACY_RECIPE_KEYS = {"teacher_forced_ratio": "whole_frame_mask_ratio"}


def _split(d: dict, source: str):
    """A config dict -> (architecture dict, recipe dict); unknown keys are errors naming both dataclasses."""
    if not isinstance(d, dict):
        raise ConfigError(f"{source}: expected a JSON object, got {type(d).__name__}")
    model_keys = {f.name for f in dataclasses.fields(GenieConfig)}
    recipe_keys = {f.name for f in dataclasses.fields(TrainingRecipe)}
    unknown = sorted(set(d) - model_keys - recipe_keys - set(LEGACY_RECIPE_KEYS))
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {unknown}; known keys: GenieConfig {sorted(model_keys)}, "
                          f"TrainingRecipe {sorted(recipe_keys)}")
    recipe = {LEGACY_RECIPE_KEYS.get(k, k): v for k, v in d.items() if k in recipe_keys or k in LEGACY_RECIPE_KEYS}
    return {k: v for k, v in d.items() if k in model_keys}, recipe


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
