"""The dynamics model's action inputs as a token dataset holds them: checking and reading the streams a config needs
(`actions/<name>.bin`, docs/formats.md), stacking them into a batch, and their normalization statistics.
genie/actions.py turns the batch's rows into embeddings.
"""
from typing import Dict, List, Optional, Tuple

import numpy as np
import torch

from common.config import load_json
from data import RawTokenDataset, TokenDatasetError
from genie.config import GenieConfig

LATENT_ACTION_NAME = "latent_action"
MIN_ACTION_STD = 1e-6  # below this a dimension is constant in the training data: it is only centred
STATS_CHUNK_ROWS = 1 << 20


def prepare_action_streams(config: GenieConfig, dataset: RawTokenDataset, require_latent: bool = True) -> bool:
    """Clear errors when the dataset lacks a stream the config's action inputs need, or has one of the wrong width;
    makes the dataset read the real streams as the model was trained on them (step means with action_step_mean).

    Returns whether the latent action ids are read (the config uses them and, unless `require_latent`, the dataset
    has them).
    """
    use_latent = config.num_latent_actions > 0 and (require_latent or LATENT_ACTION_NAME in dataset.action_dims)
    wanted = list(config.action_names or []) + ([LATENT_ACTION_NAME] if use_latent else [])
    missing = [n for n in wanted if n not in dataset.action_dims]
    if missing:
        hint = (f"; run lam/label.py to write actions/{LATENT_ACTION_NAME}.bin"
                if LATENT_ACTION_NAME in missing else "")
        raise TokenDatasetError(f"{dataset.data_dir / 'actions'}: the model needs action stream(s) "
                                f"{[n + '.bin' for n in missing]}, found {dataset.action_names or 'none'}{hint}")
    width = sum(dataset.action_dims[n] for n in config.action_names or [])
    if config.action_names and width != config.action_dim:
        raise TokenDatasetError(f"{dataset.data_dir / 'actions'}: streams {config.action_names} have {width} values "
                                f"per frame, the model expects action_dim {config.action_dim}")
    if use_latent and dataset.action_dims[LATENT_ACTION_NAME] != 1:
        raise TokenDatasetError(f"{dataset.data_dir / 'actions' / (LATENT_ACTION_NAME + '.bin')}: expected one "
                                f"id per frame, found {dataset.action_dims[LATENT_ACTION_NAME]} values")
    dataset.set_step_mean_streams(config.action_names if config.action_step_mean else ())
    return use_latent


def stack_streams(items_actions: List[Dict[str, torch.Tensor]]) -> Dict[str, torch.Tensor]:
    """Per-window action dicts (name -> (T, k), as the dataset yields them) -> name -> (B, T, k); a stream that
    only some windows have is dropped (`window_actions` then names it when the model needs it)."""
    names = set.intersection(*(set(a) for a in items_actions)) if items_actions else set()
    return {n: torch.stack([torch.as_tensor(a[n]) for a in items_actions]) for n in sorted(names)}


def window_actions(config: GenieConfig, streams: Dict[str, torch.Tensor], use_latent: bool = True,
                   where: str = "actions") -> Tuple[Optional[torch.Tensor], Optional[torch.Tensor]]:
    """A batch's action streams (name -> (B, T, k)) -> the model's inputs:
    (real actions (B, T, D) float32: the config's action_names concatenated in order, or None;
     latent action ids (B, T) int64, or None when the config has no latent actions or not `use_latent`)."""
    def stream(name: str) -> torch.Tensor:
        if name not in streams:
            raise TokenDatasetError(f"{where}: the model needs the action stream {name}.bin, but the batch has "
                                    f"{sorted(streams) or 'no actions'}")
        return streams[name].float()

    actions_BTD = torch.cat([stream(n) for n in config.action_names], dim=-1) if config.action_names else None
    latent_BT = None
    if config.num_latent_actions and use_latent:
        values_BT = stream(LATENT_ACTION_NAME)[..., 0]
        latent_BT = values_BT.round().long()
        bad = (values_BT != latent_BT) | (latent_BT < 0) | (latent_BT >= config.num_latent_actions)
        if bad.any():
            raise TokenDatasetError(f"{where}/{LATENT_ACTION_NAME}.bin: latent action ids must be integers in "
                                    f"[0, {config.num_latent_actions}), found {values_BT[bad][0].item()}")
    return actions_BTD, latent_BT


def action_statistics(dataset: RawTokenDataset, names: List[str], step_mean: bool = False
                      ) -> Tuple[List[float], List[float]]:
    """Per-dimension mean and std of the named streams over every frame of the dataset (read from the memmaps in
    chunks; with step_mean, of each frame's step mean, see RawTokenDataset); dimensions that are constant get std 1
    (centred only)."""
    mean, std = [], []
    for name in names:
        values = dataset.actions[name]
        total = np.zeros(values.shape[1])
        total_sq = np.zeros(values.shape[1])
        for a in range(0, len(values), STATS_CHUNK_ROWS):
            b = min(a + STATS_CHUNK_ROWS, len(values))
            chunk = dataset.step_mean_rows(name, np.arange(a, b)) if step_mean else values[a:b]
            chunk = np.asarray(chunk, dtype=np.float64)
            total += chunk.sum(axis=0)
            total_sq += (chunk ** 2).sum(axis=0)
        m = total / len(values)
        s = np.sqrt(np.maximum(total_sq / len(values) - m ** 2, 0.0))
        mean += m.tolist()
        std += np.where(s < MIN_ACTION_STD, 1.0, s).tolist()
    return mean, std


def latent_action_sidecar(dataset: RawTokenDataset) -> dict:
    """actions/latent_action.json written by lam/label.py (latent_action_stride,
    latent_action_num_past_frames, ...), or {} when absent."""
    path = dataset.data_dir / "actions" / f"{LATENT_ACTION_NAME}.json"
    return load_json(path, "latent action sidecar") if path.is_file() else {}


def stream_dims(dataset: RawTokenDataset, names: List[str]) -> Dict[str, int]:
    """name -> width of each requested real action stream; clear error when one is missing."""
    missing = [n for n in names if n not in dataset.action_dims]
    if missing:
        raise TokenDatasetError(f"{dataset.data_dir / 'actions'}: no action stream(s) "
                                f"{[n + '.bin' for n in missing]}; found {dataset.action_names or 'none'}")
    return {n: dataset.action_dims[n] for n in names}
