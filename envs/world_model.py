"""A trained world model as a Gymnasium environment: each `step` takes the action for the next window step and
returns the frame the model imagines after it.

    env = WorldModelEnv.from_checkpoint("data/genie_model/final_checkpt", "data/sample/val")
    frame, info = env.reset(seed=0)                        # a recorded window's first frames as the start
    frame, reward, terminated, truncated, info = env.step(np.array([0, 0, 1, 0, 0], dtype=np.int8))  # turn left

Action: for a model conditioned on the `buttons` stream alone, MultiBinary(buttons), the buttons held for the next
window step (sample_world.render.BUTTON_NAMES order); for one with other real action streams, a Box row of its
action_dim values; for a latent-action model, Discrete(num_latent_actions). Observation: the new frame decoded by
the tokenizer, (H, W, 3) uint8; info["tokens"] holds its (h, w) token ids. Reward 0, never terminated or
truncated (a task sets its own; gymnasium's TimeLimit bounds an episode).

The model sees at most T frames. The context grows from the start's frames, one frame per step, up to T-1 frames
(and the action rows between them), and the model generates the frame after it. When the window is full, the
context restarts from its last `restart_frames` frames (the config's num_prompt_frames, 8 for the sample world and the
published GENIE) and grows again: every new frame is generated as the challenge generates its futures,
frames P..T-1 after P frames. The first frame of the context gets "no action", as the first frame of every training
window does. Work is reused where the arithmetic allows it: the context's temporal keys and values are computed once
per step and shared by every MaskGIT step of the new frame, and while the context grows they are kept from step to
step; only after a restart, when every frame moves to another position embedding, is the context recomputed. That
makes a step about 1.9x faster than sliding a context of T-1 frames by one frame a step (which recomputes it every
step), with the same scores against the real frames over a minute of play (docs/experiments.md, "A context that
restarts"). genie/reference.py `next_frame_recomputed` recomputes the whole window at every MaskGIT step instead, the
published way; benchmarks/bench_play.py measures both.
"""
from typing import Optional, Sequence

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from common.errors import InputError
from data import RawTokenDataset
from sample_world.render import BUTTON_NAMES, HZ, STEP_TICS
from training.action_streams import LATENT_ACTION_NAME, prepare_action_streams
from genie.checkpoint import resolve_checkpoint_dir
from genie.config import check_dataset_matches
from genie.decoding import DecodingConfig
from genie.inference import next_frame
from genie.model import STMaskGIT

class WorldEnvError(InputError):
    """A start, an action or a setting the world model's environment cannot take."""


class WorldModelEnv(gym.Env):
    """A dynamics model (STMaskGIT) and its tokenizer (magvit2 VQModel) as an environment; see the module doc.

    starts: a token dataset whose windows (T frames at stride 15) the environment can start from, or None
    (starts from given frames only). prompt_frames: frames of a window given as the start (default: the config's
    num_prompt_frames). decoding: how each new frame is sampled (default: the model's own, `model.decoding`, which
    from_checkpoint reads from the checkpoint's decoding.json; its maskgit_steps and temperature are used, the
    MaskGIT steps unmasking at random). seed: of the sampler, when reset() gets none.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": HZ / STEP_TICS}

    def __init__(self, model: STMaskGIT, tokenizer, starts: Optional[RawTokenDataset] = None, *,
                 prompt_frames: Optional[int] = None, decoding: Optional[DecodingConfig] = None,
                 button_names: Optional[Sequence[str]] = None, render_mode: Optional[str] = None):
        config = model.config
        if render_mode not in (None, "rgb_array"):
            raise WorldEnvError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        if decoding is not None:
            model.set_decoding(decoding)
        self.model, self.tokenizer, self.render_mode = model.eval(), tokenizer.eval(), render_mode
        self.T = config.T
        self.prompt_frames = int(prompt_frames or config.num_prompt_frames or 1)
        if not 1 <= self.prompt_frames <= self.T - 1:
            raise WorldEnvError(f"prompt_frames must be in [1, {self.T - 1}], got {self.prompt_frames}")
        self.device = next(model.parameters()).device
        self.starts, self.use_latent_rows = starts, False
        if starts is not None:
            check_dataset_matches(config, starts, self.T, "the world model", exact_window=False)
            if config.uses_actions:
                self.use_latent_rows = prepare_action_streams(config, starts, require_latent=False)
        self.latent = config.num_latent_actions > 0
        self.buttons = list(config.action_names or []) == ["buttons"]
        if self.latent and config.action_dim:
            raise WorldEnvError("a model conditioned on both real and latent actions cannot be driven by one action")
        if self.latent:
            self.action_space = spaces.Discrete(config.num_latent_actions)
        elif self.buttons:
            names = list(button_names or (BUTTON_NAMES if config.action_dim == len(BUTTON_NAMES) else
                                          [f"BUTTON{i}" for i in range(config.action_dim)]))
            if len(names) != config.action_dim:
                raise WorldEnvError(f"{len(names)} button names for a model of action_dim {config.action_dim}")
            self.button_names = names
            self.action_space = spaces.MultiBinary(config.action_dim)
        elif config.action_dim:
            self.action_space = spaces.Box(-np.inf, np.inf, (config.action_dim,), dtype=np.float32)
        else:
            self.action_space = spaces.Discrete(1)  # a model without actions: one action, "go on"
        frame = self._decode(torch.zeros(config.H, config.W, dtype=torch.long, device=self.device))
        self.observation_space = spaces.Box(0, 255, frame.shape, dtype=np.uint8)
        self._generator = torch.Generator(device=self.device)
        self._tokens, self._frame, self._cache = None, None, None

    @classmethod
    def from_checkpoint(cls, checkpoint_dir, data_dir=None, tokenizer_ckpt=None, device="cpu",
                        **kwargs) -> "WorldModelEnv":
        """Load a dynamics checkpoint (a directory or a hub id; it decodes as its decoding.json says unless
        `decoding` is given), the token dataset of its starts (data_dir, or None) and the tokenizer (tokenizer_ckpt,
        else the one the dataset's metadata names, else the sample world's)."""
        from sample_world.build import SHIPPED_TOKENIZER  # the tokenizer loads only where frames are decoded
        from magvit2.model import VQModel

        model = STMaskGIT.from_pretrained(resolve_checkpoint_dir(checkpoint_dir)).to(device)
        starts = None
        if data_dir is not None:
            starts = RawTokenDataset(data_dir, window_size=model.config.T, stride=STEP_TICS, filter_overlaps=True)
            if len(starts) == 0:
                raise WorldEnvError(f"{data_dir}: no window of {model.config.T} frames at stride {STEP_TICS}")
        tokenizer_ckpt = tokenizer_ckpt or (starts.metadata.get("tokenizer_ckpt") if starts else None) \
            or SHIPPED_TOKENIZER
        tokenizer = VQModel.from_checkpoint(tokenizer_ckpt, map_location=device)
        return cls(model, tokenizer, starts, **kwargs)

    # ---------------------------------------------------------------- starts
    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """options (all optional): "window" (index of a window of `starts`; default: drawn), or "frames" ((N, H,
        W, 3) uint8 images, encoded with the tokenizer) or "tokens" ((N, h, w) ids) to start from instead (the
        last T-1 of them), with "actions" (the real action rows between them, (N-1, D); default unknown);
        "prompt_frames" (a window's frames given, default the env's)."""
        super().reset(seed=seed)
        self._generator.manual_seed(int(self.np_random.integers(0, 2**63 - 1)))
        options = dict(options or {})
        unknown = set(options) - {"window", "frames", "tokens", "actions", "prompt_frames"}
        if unknown:
            raise WorldEnvError(f"unknown reset option(s) {sorted(unknown)}: WorldModelEnv takes window, frames, "
                                f"tokens, actions, prompt_frames")
        if sum(k in options for k in ("window", "frames", "tokens")) > 1:
            raise WorldEnvError("give one of the reset options window, frames and tokens")
        window = None
        if "frames" in options or "tokens" in options:
            tokens = (self._encode(options["frames"]) if "frames" in options
                      else self._check_tokens(options["tokens"]))[-(self.T - 1):]
            n = len(tokens)
            actions = np.full((n, max(self.model.config.action_dim, 1)), np.nan, dtype=np.float32)
            if "actions" in options:  # the rows between the given frames
                actions[:-1] = self._check_rows(options["actions"], n - 1)
            latent = np.full(n, self.model.config.num_latent_actions, dtype=np.int64)
        else:
            window = self._window_index(options.get("window"))
            tokens, actions, latent = self._window_start(window, int(options.get("prompt_frames", self.prompt_frames)))
        self._tokens = torch.as_tensor(tokens, dtype=torch.long, device=self.device)
        self._actions, self._latent = torch.as_tensor(actions), torch.as_tensor(latent, dtype=torch.long)
        self._cache, self._steps, self._window = None, 0, window
        self._frame = self._decode(self._tokens[-1])
        return self._frame, self._info()

    def _window_index(self, window) -> int:
        if self.starts is None:
            raise WorldEnvError("this environment has no dataset of starts: pass options={'frames': ...} or "
                                "{'tokens': ...}, or give it a token dataset (data_dir)")
        if window is None:
            return int(self.np_random.integers(len(self.starts)))
        if isinstance(window, bool) or not isinstance(window, (int, np.integer)) or not 0 <= window < len(self.starts):
            raise WorldEnvError(f"window must be an integer in [0, {len(self.starts)}), got {window!r}")
        return int(window)

    def _window_start(self, window: int, prompt_frames: int):
        if not 1 <= prompt_frames <= self.T - 1:
            raise WorldEnvError(f"prompt_frames must be in [1, {self.T - 1}], got {prompt_frames}")
        item = self.starts[window]
        tokens = item["tokens"][:prompt_frames].numpy()
        config = self.model.config
        actions = np.full((prompt_frames, max(config.action_dim, 1)), np.nan, dtype=np.float32)
        if config.action_dim:  # rows between the given frames are known; the last one is the player's
            rows = np.concatenate([item["actions"][n].numpy() for n in config.action_names], axis=-1)
            actions[:-1] = rows[:prompt_frames - 1]
        latent = np.full(prompt_frames, config.num_latent_actions, dtype=np.int64)
        if self.use_latent_rows:  # latent row t belongs to the transition t-1 -> t, inside the given frames
            latent[1:] = item["actions"][LATENT_ACTION_NAME][1:prompt_frames, 0].numpy().round()
        return tokens, actions, latent

    @property
    def restart_frames(self) -> int:
        """Frames the context restarts from when the window is full: the config's num_prompt_frames (module doc)."""
        return self.model.config.num_prompt_frames

    def window_start_frame(self, window: int, prompt_frames: Optional[int] = None) -> int:
        """Dataset frame index of the last given frame of a start from window `window` (where the recorded walk
        goes on)."""
        return int(self.starts.valid_start_inds[window]) + ((prompt_frames or self.prompt_frames) - 1) * STEP_TICS

    def _check_rows(self, rows, n: int) -> np.ndarray:
        dim = self.model.config.action_dim
        r = np.asarray(rows, dtype=np.float32)
        if not dim or r.ndim != 2 or r.shape[1] != dim or len(r) < n:
            raise WorldEnvError(f"actions must be the {n} real action rows (n, {dim}) between the given frames "
                                f"(a model with real actions), got shape {r.shape}")
        return r[len(r) - n:]

    def _check_tokens(self, tokens) -> np.ndarray:
        config = self.model.config
        t = np.asarray(tokens)
        if t.ndim != 3 or t.shape[1:] != (config.H, config.W) or not np.issubdtype(t.dtype, np.integer) or len(t) < 1:
            raise WorldEnvError(f"tokens must be integer ids (N, {config.H}, {config.W}) with N >= 1, got "
                                f"{t.dtype} {t.shape}")
        if t.min() < 0 or t.max() >= config.image_vocab_size:
            raise WorldEnvError(f"token ids must be in [0, {config.image_vocab_size}), got [{t.min()}, {t.max()}]")
        return t.astype(np.int64)

    def _encode(self, frames) -> np.ndarray:
        f = np.asarray(frames)
        shape = self.observation_space.shape
        if f.dtype != np.uint8 or f.ndim != 4 or f.shape[1:] != shape or len(f) < 1:
            raise WorldEnvError(f"frames must be uint8 (N, {', '.join(map(str, shape))}) with N >= 1, got "
                                f"{f.dtype} {f.shape}")
        with torch.no_grad():
            return np.asarray(self.tokenizer.images_to_tokens(f[-(self.T - 1):]), dtype=np.int64)

    # ---------------------------------------------------------------- steps
    def action_row(self, action) -> torch.Tensor:
        """An action of `action_space` -> the model's row: (D,) float32 real actions, or () int64 latent id."""
        config = self.model.config
        if self.latent or not config.action_dim:
            n = config.num_latent_actions or 1
            if isinstance(action, bool) or not isinstance(action, (int, np.integer)) or not 0 <= action < n:
                raise WorldEnvError(f"action must be an integer in [0, {n}), got {action!r}")
            return torch.tensor(int(action))
        try:
            a = np.asarray(action.cpu() if isinstance(action, torch.Tensor) else action, dtype=np.float32)
        except (TypeError, ValueError):
            a = None
        if a is None or a.shape != (config.action_dim,) or not np.isfinite(a).all() or (
                self.buttons and not np.isin(a, (0.0, 1.0)).all()):
            what = f"values of 0 or 1 (one per button of {self.button_names})" if self.buttons else "finite values"
            raise WorldEnvError(f"action must be {config.action_dim} {what}, got {action!r}")
        return torch.from_numpy(a)

    def step_inputs(self, action):
        """What a step with `action` samples the next frame from: (the context's tokens (n, H, W), its action rows
        (n, D) with the last one the action's, latent ids of the n + 1 frames with the new frame's the action's).
        Once T frames are known the context restarts from the last `restart_frames` of them (module doc)."""
        if self._tokens is None:
            raise WorldEnvError("call reset() before step()")
        return self._inputs_with(self.action_row(action))

    def _inputs_with(self, row: torch.Tensor, keep: Optional[int] = None):
        """step_inputs of a model action row; keep: frames kept when the window is full (default restart_frames)."""
        tokens, actions, latent = self._tokens, self._actions.clone(), self._latent
        if len(tokens) == self.T:
            keep = keep or self.restart_frames
            tokens, actions, latent = tokens[-keep:], actions[-keep:], latent[-keep:]
        if self.model.config.action_dim:
            actions[-1] = row
        new_latent = row.view(1) if self.latent else torch.tensor([self.model.config.num_latent_actions])
        return tokens, actions, torch.cat([latent, new_latent])

    def step(self, action):
        return self._advance(*self.step_inputs(action))

    def step_row(self, row):
        """Step with a model action row instead of an action: a recorded walk's row as the dataset gives it (with
        action_step_mean, a button's share of the step's tics, so not always 0 or 1); (D,) finite values, for a
        model with real actions. What replaying a recorded walk needs (evaluation/play_protocol.py)."""
        dim = self.model.config.action_dim
        r = np.asarray(row, dtype=np.float32)
        if not dim or self.latent or r.shape != (dim,) or not np.isfinite(r).all():
            raise WorldEnvError(f"step_row needs a model with real actions and a row of {dim} finite values, got "
                                f"{row!r}")
        if self._tokens is None:
            raise WorldEnvError("call reset() before step_row()")
        return self._advance(*self._inputs_with(torch.from_numpy(r)))

    def _advance(self, tokens, actions, latent):
        # a cache that does not hold exactly this context (after a restart: none is kept) is recomputed
        decoding = self.model.decoding
        new_frame, self._cache = next_frame(self.model, tokens, actions, latent, self._cache, decoding.maskgit_steps,
                                            decoding.temperature, self._generator)
        self._tokens = torch.cat([tokens, new_frame[None]])
        self._actions = torch.cat([actions, torch.full_like(actions[:1], float("nan"))])
        self._latent = latent
        self._steps += 1
        self._frame = self._decode(new_frame)
        return self._frame, 0.0, False, False, self._info()

    def _decode(self, tokens_hw: torch.Tensor) -> np.ndarray:
        with torch.no_grad():
            return np.asarray(self.tokenizer.tokens_to_images(tokens_hw[None].to(self.device))[0].cpu())

    def _info(self) -> dict:
        return {"tokens": self._tokens[-1].cpu().numpy(), "step": self._steps, "window": self._window,
                "context_frames": len(self._tokens)}

    def render(self):
        return None if self.render_mode is None else self._frame
