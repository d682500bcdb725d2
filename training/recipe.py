"""A run's recipe in one file (recipes/*.json): the model, train.py's settings and how the trained model is sampled.

    {"model":    {GenieConfig + TrainingRecipe keys, as in genie/configs/*.json},
     "train":    {train.py flag name (without --): value},
     "decoding": {DecodingConfig fields (genie/decoding.py)}}

"model" is required; a missing "train" sets nothing and a missing "decoding" is `DecodingConfig()`. train.py checks
the "train" keys against its own flags (this module knows no argparse). Every checkpoint train.py writes keeps the
resolved recipe as recipe.json (`resolved_recipe`): the same three sections, "train" holding every flag's value.
"""
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Tuple, TypeVar

from common.config import ConfigError, load_json
from genie.config import GenieConfig, TrainingRecipe
from genie.decoding import DecodingConfig

SECTIONS = ("model", "train", "decoding")
T = TypeVar("T")


@dataclass(frozen=True)
class RunRecipe:
    """A parsed recipe file. model: the config dict (checked when loaded); train: flag name -> JSON value."""
    path: str
    model: dict
    train: dict
    decoding: DecodingConfig

    def model_config(self) -> Tuple[GenieConfig, TrainingRecipe]:
        return model_config_from_dict(self.model, f"{self.path}: model")


def load_recipe(path) -> RunRecipe:
    """Read and check a recipe file; a missing file, an unknown section or key, or a bad value is a ConfigError or
    FileNotFoundError whose one line names the file."""
    d = load_json(path, "run recipe")
    if not isinstance(d, dict):
        raise ConfigError(f"{path}: a run recipe is a JSON object with {list(SECTIONS)}, got {type(d).__name__}")
    unknown = sorted(set(d) - set(SECTIONS))
    if unknown:
        raise ConfigError(f"{path}: unknown section(s) {unknown}; a run recipe has {list(SECTIONS)}")
    if "model" not in d:
        raise ConfigError(f"{path}: a run recipe needs a \"model\" section (the GenieConfig keys)")
    for name in SECTIONS:
        if name in d and not isinstance(d[name], dict):
            raise ConfigError(f"{path}: section {name!r} must be a JSON object, got {type(d[name]).__name__}")
    recipe = RunRecipe(path=str(path), model=d["model"], train=d.get("train", {}),
                       decoding=_in_file(path, lambda: DecodingConfig.from_dict(d.get("decoding", {}),
                                                                                source=f"{path}: decoding")))
    recipe.model_config()  # unknown or bad model keys fail here, before anything is built
    return recipe


def model_config_from_dict(d: dict, source: str) -> Tuple[GenieConfig, TrainingRecipe]:
    """(architecture, training recipe) of one config dict, which holds the keys of both (as config.json does)."""
    return (_in_file(source, lambda: GenieConfig.from_dict(d, source=source)),
            _in_file(source, lambda: TrainingRecipe.from_dict(d, source=source)))


def load_model_config(path) -> Tuple[GenieConfig, TrainingRecipe]:
    """A --genie_config file: a model config JSON, or a run recipe, whose "model" section is taken."""
    d = load_json(path, "GENIE config")
    if isinstance(d, dict) and "model" in d:  # no GenieConfig field is named "model": this is a run recipe
        return load_recipe(path).model_config()
    return model_config_from_dict(d, str(path))


def resolved_recipe(config: GenieConfig, training_recipe: TrainingRecipe, train: dict,
                    decoding: DecodingConfig) -> dict:
    """What recipe.json records: the model as trained (config.json's keys, action statistics included), every
    train.py setting (made JSON-safe) and the decoding saved with the weights."""
    return {"model": {**config.to_dict(), **training_recipe.to_dict()},
            "train": {k: json_safe(v) for k, v in train.items()},
            "decoding": decoding.to_dict()}


def json_safe(value):
    """A flag's value as JSON: scalars as they are, paths as strings, sequences as lists, anything else as str."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return json_safe(dataclasses.asdict(value))
    return str(value)


def _in_file(source, build: Callable[[], T]) -> T:
    """build(), with a ConfigError's message prefixed by `source` when it does not name it yet (the dataclasses'
    own checks name only the field)."""
    try:
        return build()
    except ConfigError as e:
        message = str(e)
        raise ConfigError(message if message.startswith(str(source).split(":")[0]) else f"{source}: {message}") \
            from None
