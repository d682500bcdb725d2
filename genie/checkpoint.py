"""GENIE checkpoint directories: config.json + model.safetensors (docs/formats.md §3), plus decoding.json (how the
model is sampled) and, for a model trained here, recipe.json (the run that trained it); written atomically, read
with clear errors, from a local directory or the Hugging Face hub."""
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Optional, Union

import safetensors.torch
from huggingface_hub import hf_hub_download

from common.config import load_json
from common.errors import CheckpointError
from common.integrity import update_manifest, verify_manifest
from genie.config import GenieConfig, TrainingRecipe, save_config
from genie.decoding import DECODING_NAME, DecodingConfig, save_decoding

CONFIG_NAME = "config.json"
WEIGHTS_NAME = "model.safetensors"
RECIPE_NAME = "recipe.json"


def save_model(model, save_directory: Union[str, Path], recipe: Optional[TrainingRecipe] = None,
               run_recipe: Optional[dict] = None, decoding: Optional[DecodingConfig] = None) -> None:
    """Write config.json (+ the recipe's fields, as the published file has its training knobs),
    model.safetensors, decoding.json (`decoding`, default `model.decoding`), recipe.json (`run_recipe`, the resolved
    recipe of the run that trained it, when given) and their digests (MANIFEST.json, common/integrity.py).

    A new directory is written under a temporary name and renamed; in an existing directory each file is replaced
    atomically and other files are kept.
    """
    target = Path(save_directory)
    if target.exists() and not target.is_dir():
        raise NotADirectoryError(f"cannot save a checkpoint to {target}: it exists and is not a directory")
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        save_config(tmp / CONFIG_NAME, model.config, recipe)
        save_decoding(tmp / DECODING_NAME, model.decoding if decoding is None else decoding)
        names = [CONFIG_NAME, WEIGHTS_NAME, DECODING_NAME]
        if run_recipe is not None:
            (tmp / RECIPE_NAME).write_text(json.dumps(run_recipe, indent=2, sort_keys=True) + "\n")
            names.append(RECIPE_NAME)
        state = {k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}
        safetensors.torch.save_file(state, str(tmp / WEIGHTS_NAME), metadata={"format": "pt"})
        update_manifest(tmp, names)
        if target.exists():
            for name in names[2:] + [WEIGHTS_NAME, CONFIG_NAME]:  # config.json last, as before
                os.replace(tmp / name, target / name)
            update_manifest(target, names)
        else:
            os.replace(tmp, target)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def load_config(checkpoint_dir: Path) -> GenieConfig:
    """The GenieConfig of a checkpoint directory, parsed strictly (unknown keys are errors)."""
    config_path = Path(checkpoint_dir) / CONFIG_NAME
    return GenieConfig.from_dict(load_json(config_path, "GENIE config"), source=str(config_path))


def load_weights(model, checkpoint_dir: Path, map_location: str = "cpu") -> None:
    """Load model.safetensors into `model`; the weights must match its config key for key."""
    weights_path = Path(checkpoint_dir) / WEIGHTS_NAME
    verify_manifest(checkpoint_dir, [WEIGHTS_NAME])  # refuses silently corrupted weights (no manifest: published)
    try:
        state_dict = safetensors.torch.load_file(str(weights_path), device=str(map_location))
    except Exception as e:  # safetensors raises its own error types for truncated / non-safetensors files
        raise CheckpointError(f"{weights_path}: cannot read safetensors weights ({e})") from None
    load_state_dict_checked(model, state_dict, source=str(weights_path))


def load_state_dict_checked(model, state_dict: dict, source: str = "state dict") -> None:
    """Load weights, listing every missing / unexpected / wrongly shaped key in one clear error."""
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state_dict))
    unexpected = sorted(set(state_dict) - set(expected))
    wrong_shape = [f"{k}: checkpoint {tuple(state_dict[k].shape)} vs model {tuple(v.shape)}"
                   for k, v in expected.items() if k in state_dict and state_dict[k].shape != v.shape]
    if missing or unexpected or wrong_shape:
        problems = [f"{what} ({len(keys)}): {keys[:8]}{' ...' if len(keys) > 8 else ''}"
                    for what, keys in (("missing keys", missing), ("unexpected keys", unexpected),
                                       ("shape mismatches", wrong_shape)) if keys]
        raise CheckpointError(f"{source}: weights do not match the model built from its config "
                              f"(qk_norm={model.config.qk_norm}, num_layers={model.config.num_layers}, "
                              f"d_model={model.config.d_model}): " + "; ".join(problems))
    model.load_state_dict(state_dict)


def _looks_like_hub_id(name: str) -> bool:
    parts = name.split("/")
    return len(parts) == 2 and all(parts) and not name.startswith((".", "~")) and "\\" not in name


def resolve_checkpoint_dir(name_or_path: Union[str, Path], revision: Optional[str] = None, cache_dir=None,
                           force_download: bool = False, local_files_only: bool = False, token=None) -> Path:
    """A local checkpoint directory, or the hub cache directory of a downloaded hub id; clear errors otherwise."""
    path = Path(name_or_path)
    if path.is_dir():
        for name in (CONFIG_NAME, WEIGHTS_NAME):
            if not (path / name).is_file():
                raise FileNotFoundError(f"{path}: not a GENIE checkpoint directory ({name} is missing; expected "
                                        f"{CONFIG_NAME} and {WEIGHTS_NAME})")
        return path
    if path.exists():
        raise NotADirectoryError(f"{path}: a checkpoint must be a directory with {CONFIG_NAME} and {WEIGHTS_NAME}")
    if not _looks_like_hub_id(str(name_or_path)):
        raise FileNotFoundError(f"checkpoint directory not found: {path}")
    try:
        files = [hf_hub_download(str(name_or_path), name, revision=revision, cache_dir=cache_dir,
                                 force_download=force_download, local_files_only=local_files_only, token=token)
                 for name in (CONFIG_NAME, WEIGHTS_NAME)]
        _download_decoding(str(name_or_path), revision, cache_dir, force_download, local_files_only, token)
    except Exception as e:  # offline, unknown repo, no access, invalid id: all end the same way for the user
        raise FileNotFoundError(
            f"checkpoint {name_or_path!r} is not a local directory and could not be fetched from the Hugging Face "
            f"hub ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}). On a machine with internet, "
            f"download it with `huggingface-cli download {name_or_path} --local-dir <dir>` and pass that "
            f"directory instead.") from None
    return Path(files[0]).parent


def _download_decoding(repo_id: str, revision, cache_dir, force_download: bool, local_files_only: bool, token) -> None:
    """Fetch a hub checkpoint's decoding.json beside its weights when it has one (the published ones do not)."""
    from huggingface_hub.utils import EntryNotFoundError

    try:
        hf_hub_download(repo_id, DECODING_NAME, revision=revision, cache_dir=cache_dir, force_download=force_download,
                        local_files_only=local_files_only, token=token)
    except EntryNotFoundError:
        pass
