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
latent id `num_latent_actions` are unknown too (e.g. to play latent actions while real ones stay unknown).
Teacher-forced evaluation of target t knows
rows < t (the real action of frame t-1, not the latent action derived from frame t itself); generation from a
P-frame prompt knows rows < P unless the caller plays actions (control).

Reading these streams from a token dataset is training/action_streams.py's job; this file is only the network part.
"""
from typing import Optional, Union

import torch
from torch import nn

from genie.config import GenieConfig


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
