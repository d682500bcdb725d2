"""Action inputs of the dynamics model (Genie's additive conditioning): real actions and LAM latent actions.

Both come as per-frame streams in the token dataset layout (row t belongs to window frame t):
- real actions (B, T, D), the config's `action_names` streams concatenated: row t is the command issued at frame
  t, which drives the transition t -> t+1, so frame t's tokens get + action_proj(normalized row t-1);
- latent actions (B, T) ids from actions/latent_action.bin (lam/label.py): row t is the LAM's code
  of the transition t-1 -> t, so frame t's tokens get + latent_action_embed(row t).
Frame 0 and every unknown row get "no action": a learned `null_action_embed`, and the extra latent id
`num_latent_actions`.

Which rows are known is explicit, so nothing leaks: `known_T[t]` is the number of leading rows that frame t may
use (rows >= known_T[t] are treated as unknown whatever their values). A real action row holding NaN and the
latent id `num_latent_actions` are unknown too (e.g. to play latent actions while real ones stay unknown). Teacher-forced evaluation of target t knows
rows < t (the real action of frame t-1, not the latent action derived from frame t itself); generation from a
P-frame prompt knows rows < P unless the caller plays actions (control).
"""
from typing import Dict, List, Optional, Tuple, Union

import numpy as np
import torch
from torch import nn

from data import RawTokenDataset, TokenDatasetError
from genie.config import GenieConfig, load_json

LATENT_ACTION_NAME = "latent_action"
MIN_ACTION_STD = 1e-6  # below this a dimension is constant in the training data: it is only centred
STATS_CHUNK_ROWS = 1 << 20


class ActionConditioning(nn.Module):
    """Per-frame action embeddings (B, T, C) added to every token of the frame."""

    def __init__(self, config: GenieConfig):
        super().__init__()
        self.action_dim, self.num_latent_actions = config.action_dim, config.num_latent_actions
        self.dropout = config.action_dropout
        if self.action_dim:
            self.action_proj = nn.Linear(self.action_dim, config.d_model)
            self.null_action_embed = nn.Parameter(torch.zeros(1, config.d_model))
            # normalization statistics live in the config (config.json), not in the weights
            mean = config.action_mean or [0.0] * self.action_dim
            std = config.action_std or [1.0] * self.action_dim
            self.register_buffer("action_mean", torch.tensor(mean, dtype=torch.float32), persistent=False)
            self.register_buffer("action_std", torch.tensor(std, dtype=torch.float32), persistent=False)
        if self.num_latent_actions:
            self.latent_action_embed = nn.Embedding(self.num_latent_actions + 1, config.d_model)  # last id: none

    def check_inputs(self, actions_BTD: Optional[torch.Tensor], latent_actions_BT: Optional[torch.Tensor],
                     B: int, T: int) -> None:
        """Clear errors for action inputs that do not fit the model or the window of B x T frames."""
        if actions_BTD is not None:
            if not self.action_dim:
                raise ValueError("real actions given, but the model has no action input (config.action_names)")
            if actions_BTD.shape != (B, T, self.action_dim) or not actions_BTD.is_floating_point():
                raise ValueError(f"actions must be float (B, T, D) = ({B}, {T}, {self.action_dim}), got "
                                 f"{actions_BTD.dtype} {tuple(actions_BTD.shape)}")
            if actions_BTD.isinf().any():
                raise ValueError("actions must be finite (NaN marks an unknown row), got inf")
        if latent_actions_BT is not None:
            K = self.num_latent_actions
            if not K:
                raise ValueError("latent actions given, but the model has no latent action input "
                                 "(config.num_latent_actions is 0)")
            if latent_actions_BT.shape != (B, T) or latent_actions_BT.is_floating_point():
                raise ValueError(f"latent actions must be integer ids (B, T) = ({B}, {T}), got "
                                 f"{latent_actions_BT.dtype} {tuple(latent_actions_BT.shape)}")
            if ((latent_actions_BT < 0) | (latent_actions_BT > K)).any():
                raise ValueError(f"latent action ids must be in [0, {K}) ({K} = no action), got values in "
                                 f"[{latent_actions_BT.min().item()}, {latent_actions_BT.max().item()}]")

    def forward(self, B: int, T: int, actions_BTD: Optional[torch.Tensor], latent_actions_BT: Optional[torch.Tensor],
                known_T: Union[int, torch.Tensor], device: torch.device) -> torch.Tensor:
        """Action embeddings (B, T, C) of window frames 0..T-1; known_T: int or (T,) known rows per frame."""
        t_T = torch.arange(T, device=device)
        known_T = torch.as_tensor(known_T, device=device)
        drop_BT = torch.zeros(B, T, dtype=torch.bool, device=device)
        if self.training and self.dropout > 0:  # classifier-free style: the model also learns "no action"
            drop_BT = torch.rand(B, T, device=device) < self.dropout
        embeds_BTC = 0
        if self.action_dim:
            use_BT = ((t_T >= 1) & (t_T - 1 < known_T)) & ~drop_BT
            null_BTC = self.null_action_embed.expand(B, T, -1)
            if actions_BTD is None:
                embeds_BTC = null_BTC
            else:
                previous_BTD = torch.cat([torch.zeros_like(actions_BTD[:, :1]), actions_BTD[:, :-1]], dim=1)
                use_BT = use_BT & ~previous_BTD.isnan().any(dim=-1)
                normalized_BTD = ((previous_BTD - self.action_mean) / self.action_std).masked_fill(~use_BT[..., None],
                                                                                                   0.0)
                projected_BTC = self.action_proj(normalized_BTD)
                embeds_BTC = torch.where(use_BT[..., None], projected_BTC, null_BTC.to(projected_BTC.dtype))
        if self.num_latent_actions:
            K = self.num_latent_actions
            use_BT = ((t_T >= 1) & (t_T < known_T)) & ~drop_BT
            ids_BT = (torch.full((B, T), K, dtype=torch.long, device=device) if latent_actions_BT is None
                      else torch.where(use_BT, latent_actions_BT.long(), K))
            embeds_BTC = embeds_BTC + self.latent_action_embed(ids_BT)
        return embeds_BTC


# ---------------------------------------------------------------- reading actions from a token dataset
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
