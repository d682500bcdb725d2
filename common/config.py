"""Strict JSON configs: dataclasses built from JSON dicts where unknown keys and wrong types are errors."""
import dataclasses
import json
import math
import typing
from pathlib import Path
from typing import Any

from common.errors import InputError


class ConfigError(InputError):
    """A config file or dict that does not describe a valid model."""


def _check_type(name: str, value: Any, annotation: Any, source: str) -> Any:
    """Coerce JSON values to the field's type; raise ConfigError naming the field when they do not fit."""
    origin = typing.get_origin(annotation)
    if origin is typing.Union:  # Optional[X]
        if value is None:
            return None
        annotation = next(a for a in typing.get_args(annotation) if a is not type(None))
    if annotation is bool:
        if isinstance(value, bool):
            return value
    elif annotation is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
    elif annotation is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
    elif annotation is str:
        if isinstance(value, str):
            return value
    elif typing.get_origin(annotation) in (list, tuple) or annotation in (list, tuple):
        if isinstance(value, (list, tuple)):
            return list(value)
    else:
        return value
    raise ConfigError(f"{source}: field {name!r} must be {getattr(annotation, '__name__', annotation)}, got {value!r}")


def dataclass_from_dict(cls, d: dict, source: str = "config"):
    """Build dataclass `cls` from a JSON dict: unknown keys and wrong types are errors that name `source`."""
    if not isinstance(d, dict):
        raise ConfigError(f"{source}: expected a JSON object, got {type(d).__name__}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(d) - names)
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {unknown} for {cls.__name__}; known keys: {sorted(names)}")
    kwargs = {k: _check_type(k, v, hints[k], source) for k, v in d.items()}
    try:
        return cls(**kwargs)
    except TypeError as e:  # missing required fields
        raise ConfigError(f"{source}: {e}") from None


def load_json(path, what: str = "config") -> dict:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ConfigError(f"{path}: not valid JSON ({e})") from None
