"""The sample world itself as a Gymnasium environment: the walker's ViZDoom renderer and frame processing, driven
by held buttons for one window step (15 tics, the stride between a token dataset window's frames) per `step`.

Its actions mean what the world model's environment (envs/world_model.py) means by them, so a player or a policy
that drives one drives the other. A start is a recorded walk's frame: the walk's episode seed replays the same
warm-up and explorer tics (`sample_world.render.start_walk`), so `reset(options={"map": "MAP18", "episode_seed": s,
"frame": k})` shows frame k of the walk recorded with seed s; `recorded_start` finds those three for a frame of a
built world.

    env = DoomEnv(maps=["MAP18"])
    frame, info = env.reset(seed=0)
    frame, reward, terminated, truncated, info = env.step(np.array([1, 0, 0, 0, 0], dtype=np.int8))  # forward
"""
import json
import math
import tempfile
import weakref
from pathlib import Path
from typing import Optional, Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from common.errors import InputError
from sample_world.render import (BUTTON_NAMES, HZ, MAX_STEP, SIDECAR_NAME, STEP_TICS, VAL_MAPS,  # noqa: F401
                                 WorldConfig, buttons_from_names, check_maps, engine_action, gamma_table, make_game,
                                 preprocess_frame, sidecar_world_config, start_walk)

MAX_START_FRAME = 1500  # recorded tics a random start walks before it begins (a recorded walk's length)


class EnvInputError(InputError):
    """An action or a reset option that the environment cannot take."""


def check_buttons(action, num_buttons: int) -> np.ndarray:
    """A MultiBinary action (sequence of 0/1) -> int8 (num_buttons,); clear error otherwise."""
    a = np.asarray(action)
    if a.shape != (num_buttons,) or not np.isin(a, (0, 1)).all():
        raise EnvInputError(f"action must be {num_buttons} values of 0 or 1 (one per button "
                            f"{list(BUTTON_NAMES)[:num_buttons]}), got {action!r}")
    return a.astype(np.int8)


def world_config(raw_dir) -> WorldConfig:
    """The WorldConfig a sample world was rendered with (raw_dir/sample_world.json), its walker included: an older
    world's walker replays its recorded walks (sample_world.render.sidecar_world_config)."""
    path = Path(raw_dir) / SIDECAR_NAME
    if not path.is_file():
        raise EnvInputError(f"{path} not found: not the raw folder of a sample world (sample_world.build writes it)")
    return sidecar_world_config(json.loads(path.read_text()))


def recorded_start(raw_npz, frame_index: int) -> dict:
    """Where frame `frame_index` of a rendered split (raw/train.npz or raw/val.npz, in the token dataset's frame
    order) was recorded: {"map", "episode_seed", "frame"} (frame: its index within its walk), DoomEnv's reset
    options for that frame."""
    with np.load(raw_npz) as npz:
        segment_ids, maps, seeds = npz["segment_ids"], npz["maps"], npz["episode_seeds"]
    if not 0 <= frame_index < len(segment_ids):
        raise EnvInputError(f"{raw_npz}: frame {frame_index} out of range [0, {len(segment_ids)})")
    episode = int(segment_ids[frame_index])
    first = int(np.searchsorted(segment_ids, episode))
    return {"map": str(maps[episode]), "episode_seed": int(seeds[episode]), "frame": frame_index - first}


class DoomEnv(gym.Env):
    """The sample world's walker, one window step per `step`.

    Observation: the (S, S, 3) uint8 frame as the datasets record it. Action: MultiBinary(5), the buttons held for
    the whole step in BUTTON_NAMES order. Reward 0 (a task sets its own); terminated when the level ends (an exit
    was used) or a teleporter moved the player (as the recorded walks end there: no world model was shown where one
    leads; the frame and pose stay those before it, and info["teleported"] is True); never truncated (wrap it in
    gymnasium's TimeLimit). After the end, steps keep the last frame and pose. info: "pose" (x, y, heading in degrees),
    "map", "episode_seed", "frame" (recorded tics walked before the start) and, after a step, "motion" (the
    step's displacement along the start heading in map units and its turn in degrees, counter-clockwise positive).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": HZ / STEP_TICS}

    def __init__(self, maps: Sequence[str] = VAL_MAPS, cfg: Optional[WorldConfig] = None,
                 step_tics: int = STEP_TICS, render_mode: Optional[str] = None):
        if render_mode not in (None, "rgb_array"):
            raise EnvInputError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.maps = list(maps)
        check_maps(self.maps)
        self.cfg = cfg or WorldConfig()
        self.step_tics, self.render_mode = int(step_tics), render_mode
        S = self.cfg.frame_size
        self.observation_space = spaces.Box(0, 255, (S, S, 3), dtype=np.uint8)
        self.action_space = spaces.MultiBinary(len(BUTTON_NAMES))
        self._gamma_lut = gamma_table(self.cfg.gamma)
        workdir = tempfile.TemporaryDirectory(prefix="vizdoom.", ignore_cleanup_errors=True)
        self._workdir, self._games = workdir.name, []  # the engine (at most one), closed before its folder goes
        self._shutdown = weakref.finalize(self, _shut_down, self._games, workdir)
        self._map, self._frame, self._start, self._explorer, self._last_pose = None, None, {}, None, None
        self._ended = False

    @property
    def _game(self):
        return self._games[0] if self._games else None

    def _game_on(self, map_name: str):
        if self._map != map_name:
            self.close_game()
            self._games.append(make_game(map_name, self.cfg, workdir=self._workdir))
            self._map = map_name
        return self._game

    def _pose(self) -> tuple:
        # a level left through its exit has no state, and a teleporter's far side is no walk: the pose stays where
        # the walk ended
        if not (self._ended or self._game.is_episode_finished()):
            self._last_pose = tuple(float(v) for v in self._game.get_state().game_variables)
        return self._last_pose

    def _observe(self) -> np.ndarray:
        self._frame = preprocess_frame(self._game.get_state().screen_buffer, self.cfg.frame_size, self._gamma_lut)
        return self._frame

    def reset(self, *, seed: Optional[int] = None, options: Optional[dict] = None):
        """options (all optional): "map" (default: one of `maps`, drawn), "episode_seed" (default: drawn),
        "frame" (recorded tics to walk after the warm-up, default: drawn in [0, 1500))."""
        super().reset(seed=seed)
        options = dict(options or {})
        unknown = set(options) - {"map", "episode_seed", "frame"}
        if unknown:
            raise EnvInputError(f"unknown reset option(s) {sorted(unknown)}: DoomEnv takes map, episode_seed, frame")
        map_name = options.get("map", self.maps[int(self.np_random.integers(len(self.maps)))])
        episode_seed = int(options.get("episode_seed", self.np_random.integers(0, 2**32 - 1)))
        frame = int(options.get("frame", self.np_random.integers(0, MAX_START_FRAME)))
        if frame < 0:
            raise EnvInputError(f"frame must be >= 0, got {frame}")
        self._explorer, self._ended = start_walk(self._game_on(map_name), episode_seed, self.cfg), False
        self._start = {"map": map_name, "episode_seed": episode_seed, "frame": frame}
        self.follow_explorer(frame)  # the explorer's recorded tics up to the start frame
        return self._observe(), {**self._start, "pose": self._pose()}

    def follow_explorer(self, tics: int) -> np.ndarray:
        """Go on with the recorded walk (the explorer that walked it) for `tics` tics; returns the buttons it held,
        (tics, 5) float32. The frame after them is `render()`'s / the next observation."""
        game, held = self._game, []
        for _ in range(tics):
            if game.is_episode_finished():
                break
            state = game.get_state()
            buttons = self._explorer(state.depth_buffer, state.game_variables[:2])
            held.append(buttons)
            game.make_action(engine_action(buttons, self.cfg))
        if game.is_episode_finished():
            raise EnvInputError(f"{self._start['map']}: the walk of seed {self._start['episode_seed']} ends before "
                                f"frame {self._start['frame']} + {tics} tics")
        self._observe()
        return np.asarray(held, dtype=np.float32).reshape(tics, len(BUTTON_NAMES))

    def step(self, action):
        if self._game is None or self._frame is None:
            raise EnvInputError("call reset() before step()")
        buttons = check_buttons(action, len(BUTTON_NAMES))
        ended = {**self._start, "pose": self._last_pose, "motion": (0.0, 0.0)}
        if self._ended or self._game.is_episode_finished():
            return self._frame, 0.0, True, False, ended
        x0, y0, a0 = self._pose()
        command = engine_action(tuple(int(b) for b in buttons), self.cfg)
        for _ in range(self.step_tics):  # one tic at a time: delta inputs act per tic
            self._game.make_action(command)
            if self._game.is_episode_finished():
                self._ended = True
                return self._frame, 0.0, True, False, ended
        x1, y1, a1 = pose = self._pose()
        turn = (a1 - a0 + 180.0) % 360.0 - 180.0
        if self._teleported(math.hypot(x1 - x0, y1 - y0), turn, buttons):
            self._ended, self._last_pose = True, (x0, y0, a0)
            return self._frame, 0.0, True, False, {**ended, "pose": self._last_pose, "teleported": True}
        heading = math.radians(a0)
        motion = ((x1 - x0) * math.cos(heading) + (y1 - y0) * math.sin(heading), turn)
        return self._observe(), 0.0, False, False, {**self._start, "pose": pose, "motion": motion}

    def _teleported(self, distance: float, turn: float, buttons: np.ndarray) -> bool:
        """No walk covers `distance` in a step (Doom caps momentum at MAX_STEP a tic), and a held turn button turns
        exactly turn_speed a tic: anything else is a teleporter."""
        held_turn = (int(buttons[2]) - int(buttons[3])) * self.cfg.turn_speed * self.step_tics
        off = abs((turn - held_turn + 180.0) % 360.0 - 180.0)
        return distance > MAX_STEP * self.step_tics or off > 1.0

    def render(self):
        return None if self.render_mode is None else self._frame

    @property
    def frame(self) -> np.ndarray:
        """The latest observation."""
        return self._frame

    @property
    def pose(self) -> tuple:
        """(x, y, heading in degrees) now."""
        return self._pose()

    def close_game(self) -> None:
        while self._games:
            self._games.pop().close()
        self._map = None

    def close(self):
        self._shutdown()  # the engine, then its folder; also at garbage collection or exit if never called
        super().close()


def _shut_down(games: list, workdir: tempfile.TemporaryDirectory) -> None:
    while games:
        games.pop().close()
    workdir.cleanup()
