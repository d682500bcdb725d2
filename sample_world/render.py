"""Sample world: first-person walks through Freedoom 2 maps rendered headless by ViZDoom, with per-frame actions.

The offline stand-in for the 1X robot videos: an explorer policy walks through maps with no monsters, HUD, weapon
or sound, and every game tic (35 Hz, so the challenge's 16-frame windows at stride 15 span 6.9 s) we record a
64x64 RGB frame (160x120 render, centre crop 120x120, area resize, gamma 1.5), the buttons held, the velocity they
command (`driving_command`) and the motion measured. Each split is one .npz:
- `frames` (N, 64, 64, 3) uint8; `segment_ids` (N,) int32, one id per episode, increasing; `hz` = 35;
  `maps` (E,) and `episode_seeds` (E,) per episode; `button_names`.
- `actions_buttons` (N, 5) float32 0/1 in the order MOVE_FORWARD, MOVE_BACKWARD, TURN_LEFT, TURN_RIGHT, USE:
  row t is what was held during the tic that leads from frame t to frame t+1.
- `actions_driving_command` (N, 2) float32 = the (linear, angular) velocity those buttons command, as the 1X robot's
  `driving_command` is its commanded base velocity: linear = (forward - backward) x the walker's top speed (145.8 map
  units/s; 64 units ~ 2 m), angular = (left - right) x its turn rate (0.53 rad/s, counter-clockwise positive). What a
  player or a policy can say, so what a model that one drives is conditioned on.
- `actions_measured_motion` (N, 2) float32 = the (linear, angular) velocity measured over that same tic, the forward
  difference of the pose from frame t to frame t+1: displacement projected on the heading at frame t in map units/s
  (Doom momentum makes it ramp up and coast for a few tics, and a wall stops it), heading change in rad/s. An
  outcome, not a command: it already knows about the wall ahead, so it is for evaluation, never a model's input.
- `poses` (N, 3) float32 = (x, y, heading in degrees) at frame t.
No strafing, so (linear, angular) fully describes the motion, as for a wheeled base. The walker moves at half of
Doom's walking speed and turns at a quarter of its turning speed (ViZDoom delta inputs; 30 degrees/s, a mobile
robot's pace rather than a gamer's), so that one model step (15 tics) turns the view at most 13 degrees and moves it
at most ~62 units instead of 53 degrees and 125: consecutive model frames overlap well. WorldConfig(turn_speed=1.75)
gives the walker of earlier versions (26 degrees per step).

The walker (`ExplorerPolicy`) explores: it mostly walks forward, curves away from walls ahead and turns in place
when one is close (the depth buffer). A policy suite and a player use every button, and a model learns only what
its windows show (one button row every 15 tics), so since version 3 the walker also holds, each for at least one
window step (15-45 tics): backward walks (alone or with a turn), no button at all, backing away from a wall while
turning, a forward walk turned straight into a backward one (shuttling), and USE at walls ahead (walking up to
within reach and, since version 4, standing until the view is still; with or without forward, then waiting while a
door, if it is one, opens). Over the tics of a split, about: forward (with or without a turn) 40 %, turn in place
33 %, backward 11 %, no button 13 %, USE 4.5 %;
the sidecar records each split's shares (`button_stats`). Version 2's walker (V2_WALKER) pressed backward in 1 % of
the tics, USE for single tics (which windows almost never show) and never stood still.

Episodes start at a random deathmatch spawn spot (chosen by the engine seed) after an unrecorded warm-up walk of
random length, in god mode (damaging floors). An episode that a teleporter or a level exit cuts short, or whose
walker stays trapped in a closet, is replayed with the next seed (is_good_episode). Validation = held-out episodes
(other seeds) on VAL_MAPS: the first eight training maps plus HELDOUT_MAPS, a map never seen in training.

Usage:
    python -m sample_world.render --output_dir data/sample/raw --seed 0
"""
import argparse
import dataclasses
import json
import math
import multiprocessing
import os
import struct
import sys
import tempfile
import time
import zlib
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
from PIL import Image
from tqdm import tqdm

from common.cli import add_hidden_alias, non_negative_int, positive_int, run_main
from common.errors import InputError
from common.shutdown import exit_on_sigterm, stop_pool

HZ = 35  # Doom's fixed tic rate; we record every tic.
STEP_TICS = 15  # tics between the frames of a token dataset window (its stride): one step of a player or a policy
BUTTON_NAMES = ("MOVE_FORWARD", "MOVE_BACKWARD", "TURN_LEFT", "TURN_RIGHT", "USE")
# Maps that render well (light, room to walk); the held-out map is never used for training. The world began with
# the first eight; the other eight share no map with any unseen set (build.sh --unseen), and twice the maps at the
# same frames per map beat the eight on every unseen set (docs/experiments.md).
TRAIN_MAPS = ("MAP01", "MAP04", "MAP05", "MAP09", "MAP10", "MAP12", "MAP13", "MAP15",
              "MAP08", "MAP11", "MAP14", "MAP16", "MAP17", "MAP19", "MAP20", "MAP21")
HELDOUT_MAPS = ("MAP18",)
# Validation walks: held-out episodes on the first eight training maps (the original world's, so that validation
# numbers stay comparable across versions) and on the held-out map.
VAL_MAPS = TRAIN_MAPS[:8] + HELDOUT_MAPS
MAX_STEP = 30.0  # map units per tic; Doom caps momentum here, so a longer step is a teleport
GENERATOR_VERSION = 4  # bump when a change in this file changes the generated data
SIDECAR_NAME = "sample_world.json"
STATS_KEY = "button_stats"  # the sidecar's key of what was generated (the rest: what was asked for)
STALL_TIMEOUT_S = 600.0  # seconds without a finished task before a worker pool is declared stuck (a task: ~5 s)


def raw_frames_path(data_dir) -> Path:
    """Where a sample world keeps the real frames of its token dataset `<root>/<split>`: `<root>/raw/<split>.npz`
    (sample_world.build writes both; other data, such as the 1X release, has tokens only)."""
    data_dir = Path(data_dir)
    return data_dir.parent / "raw" / f"{data_dir.name}.npz"


class ButtonsError(InputError):
    """Button names the sample world does not have."""


def buttons_from_names(names: Sequence[str], button_names: Sequence[str] = BUTTON_NAMES) -> np.ndarray:
    """Held button names (e.g. ["MOVE_FORWARD", "TURN_LEFT"]) -> a 0/1 int8 vector in `button_names` order."""
    if not isinstance(names, (list, tuple)) or not all(isinstance(n, str) for n in names):
        raise ButtonsError(f"action must be a list of button names, got {names!r}")
    unknown = [n for n in names if n not in button_names]
    if unknown:
        raise ButtonsError(f"unknown button(s) {unknown}: the buttons are {list(button_names)}")
    return np.array([int(b in names) for b in button_names], dtype=np.int8)

# Macro actions of the explorer: which buttons each one holds (order of BUTTON_NAMES).
_ACTIONS = {
    "forward": (1, 0, 0, 0, 0),
    "forward_left": (1, 0, 1, 0, 0),
    "forward_right": (1, 0, 0, 1, 0),
    "left": (0, 0, 1, 0, 0),
    "right": (0, 0, 0, 1, 0),
    "backward": (0, 1, 0, 0, 0),
    "backward_left": (0, 1, 1, 0, 0),
    "backward_right": (0, 1, 0, 1, 0),
    "stand": (0, 0, 0, 0, 0),
    "approach": (1, 0, 0, 0, 0),  # walking up to a wall to press USE on it
}
_FORWARD_ACTIONS = ("forward", "forward_left", "forward_right")

@dataclass
class WorldConfig:
    """Rendering and explorer-policy settings. Depth thresholds are in depth-buffer units (about 8 map units each)."""

    frame_size: int = 64  # output frames are frame_size x frame_size RGB
    gamma: float = 1.5  # brighten Doom's dark sectors (like its own gamma-correction setting); 1 = unchanged
    walk_speed: float = 12.5  # forward/backward input while a move button is held (Doom's walk is 25)
    turn_speed: float = 0.875  # degrees per tic while a turn button is held (Doom's turn is 3.5)
    warmup_min_tics: int = 35  # unrecorded warm-up walk of random length in [min, max] tics (the player is
    warmup_max_tics: int = 400  # frozen for the first few tics of an episode)
    near_depth: int = 12  # obstacle closer than this straight ahead: turn in place ...
    clear_depth: int = 20  # ... until the way ahead is free at least this far (version 2: 28, longer turns)
    caution_depth: int = 20  # closer than this: curve away while walking
    stuck_window: int = 12  # tics of forward motion over which we check progress
    stuck_distance: float = 10.0  # map units; less progress than this over the window means stuck
    open_side_prob: float = 0.7  # chance that a random turn goes towards the more open side
    # What the walker does when a hold expires: weights of the macro actions (forward, forward + a turn, a turn in
    # place, backward, no button), and how long the sticky ones last: at least one window step, so models see them.
    forward_weight: float = 0.55
    curve_weight: float = 0.25
    turn_weight: float = 0.04  # walls make turns in place plenty (avoid, turn around)
    backward_weight: float = 0.06
    stand_weight: float = 0.2
    sticky_min_tics: int = 15  # a backward walk, a stand or a backing away lasts [min, max] tics
    sticky_max_tics: int = 45
    backward_turn_share: float = 0.4  # share of the sampled backward walks that hold a turn too
    reverse_prob: float = 0.15  # chance that an expiring forward hold turns straight into a backward one (shuttle)
    avoid_backward_prob: float = 0.5  # chance that a turn away from a wall (avoid, turn around) backs away first
    # USE: at a wall ahead (a door, perhaps) and when stuck.
    door_use_prob: float = 0.35  # chance that a wall ahead gets a USE: walk up to it, then press
    door_depth: int = 6  # walk up until the wall is this close (~48 units; Doom's USE reaches 64) ...
    approach_tics: int = 30  # ... or for at most this long
    use_cooldown_tics: int = 105  # no USE at a wall this soon after the last one (a wall that is no door)
    use_prob: float = 0.5  # chance to press USE when stuck
    use_hold_tics: int = 15  # tics USE is held (Doom presses once per hold): a whole window step
    use_wait_tics: int = 30  # a USE lasts this long: held for use_hold_tics, then waiting while a door opens
    use_alone_share: float = 0.5  # share of the USEs with no other button (the rest push forward, waiting too)
    # tics standing still (no button) before USE is pressed, so that a USE alone shows a view that stays put: a walker
    # that presses it as it arrives coasts ~40 units on (version 3: a USE step moved a quarter of a forward step)
    use_settle_tics: int = 20
    max_attempts: int = 4  # seeds tried per episode until one passes is_good_episode
    min_episode_frac: float = 0.5  # shorter walks (cut by a teleporter or a level exit) are retried
    min_cells_per_1000_tics: float = 8.0  # fewer distinct 64x64-unit cells visited means trapped: retried

    def __post_init__(self):
        if self.frame_size < 8 or self.gamma <= 0:
            raise ValueError(f"WorldConfig needs frame_size >= 8 and gamma > 0, got {self.frame_size}, {self.gamma}")
        if not 0 < self.near_depth < self.caution_depth <= self.clear_depth:
            raise ValueError("WorldConfig needs 0 < near_depth < caution_depth <= clear_depth")
        if not self.turn_speed > 0:
            raise ValueError(f"WorldConfig needs turn_speed > 0 (degrees per tic), got {self.turn_speed}")
        if not self.walk_speed > 0:
            raise ValueError(f"WorldConfig needs walk_speed > 0, got {self.walk_speed}")
        if not 1 <= self.sticky_min_tics <= self.sticky_max_tics:
            raise ValueError(f"WorldConfig needs 1 <= sticky_min_tics <= sticky_max_tics, got "
                             f"{self.sticky_min_tics}, {self.sticky_max_tics}")
        if self.use_settle_tics < 0:
            raise ValueError(f"WorldConfig needs use_settle_tics >= 0, got {self.use_settle_tics}")
        if not 1 <= self.use_hold_tics <= self.use_wait_tics:
            raise ValueError(f"WorldConfig needs 1 <= use_hold_tics <= use_wait_tics, got {self.use_hold_tics}, "
                             f"{self.use_wait_tics}")

    @property
    def top_speed(self) -> float:
        """Map units/s the walker reaches holding a move button: Doom thrusts walk_speed x 2048 / 65536 units per
        tic against a friction that keeps 0.90625 of the momentum each tic."""
        return self.walk_speed * (2048 / 65536) / (1 - 0.90625) * HZ

    @property
    def turn_rate(self) -> float:
        """Radians/s the view turns while a turn button is held."""
        return math.radians(self.turn_speed) * HZ


# The settings added in generator version 4 at the values that make its walker the version-3 one, and those added in
# version 3 at the values that make it the version-2 one, exactly (every behaviour added is off and draws no random
# number): worlds built before were walked by those walkers, and the real world (envs/doom.py) replays their
# recorded walks to start from their frames.
V3_WALKER = {"use_settle_tics": 0}
V2_WALKER = {**V3_WALKER, "use_wait_tics": 30, "use_hold_tics": 1, "use_alone_share": 0.0, "door_use_prob": 0.0,
             "stand_weight": 0.0, "backward_turn_share": 0.0, "sticky_min_tics": 6, "sticky_max_tics": 20,
             "reverse_prob": 0.0, "avoid_backward_prob": 0.0}


def sidecar_world_config(sidecar: dict) -> WorldConfig:
    """The WorldConfig a sample world was walked with, from its sidecar (sample_world.json): its recorded settings,
    with the older walkers' (V2_WALKER, V3_WALKER) for the settings a world of an older generator version does not
    name."""
    config = sidecar["config"]
    version = sidecar.get("generator_version", 0)
    if version < 4:
        config = {**(V2_WALKER if version < 3 else V3_WALKER), **config}
    return WorldConfig(**config)


def _hold(rng: np.random.Generator, lo: int, hi: int) -> int:
    return int(rng.integers(lo, hi + 1))


def _chance(rng: np.random.Generator, p: float) -> bool:
    """True with probability p; a zero p draws no number, so that a behaviour switched off leaves the random stream
    (and so the walk) as it was: the version-2 walker is this one with V2_WALKER's settings."""
    return p > 0 and rng.random() < p


class ExplorerPolicy:
    """Sticky-action walker that prefers moving forward and steers away from near walls using the depth buffer;
    now and then it walks backward, stands, shuttles, and presses USE at walls (module doc).

    Call it once per tic with the depth buffer (H, W) uint8 (larger = farther) and the player's (x, y); it returns
    the buttons to hold for that tic as a tuple of 0/1 in BUTTON_NAMES order.
    """

    def __init__(self, cfg: WorldConfig, rng: np.random.Generator):
        self.cfg = cfg
        self.rng = rng
        self.action = "forward"
        self.hold = _hold(rng, 10, 40)
        self.avoid_side: Optional[str] = None  # turn direction kept while avoiding, so we do not oscillate
        self.forward_xy = deque(maxlen=cfg.stuck_window)
        self.just_used = False
        self.spin_tics = 0  # tics spent turning away from walls without finding an opening
        self.trapped_tics = int(360 / cfg.turn_speed)  # a full turn without an opening: try USE (a closed door?)
        self.turn_around_tics = (int(100 / cfg.turn_speed), int(180 / cfg.turn_speed))
        self.back_tics = 0  # tics left backing away from a wall before turning in place
        self.use_tics = 0  # tics left holding USE
        self.use_forward = True  # whether the USE pushes forward
        self.since_use = cfg.use_cooldown_tics  # tics since the last USE

    def _depth_features(self, depth_HW: np.ndarray):
        H, W = depth_HW.shape
        band = depth_HW[int(H * 0.42): int(H * 0.58)]  # rows around the horizon: walls, not floor or ceiling
        c0, c1 = int(W * 0.375), int(W * 0.625)
        ahead = int(band[:, c0:c1].min())
        left, right = float(band[:, :c0].mean()), float(band[:, c1:].mean())
        return ahead, ("left" if left >= right else "right")

    def _start(self, action: str, hold: int):
        self.action, self.hold = action, hold
        self.back_tics = 0
        self.forward_xy.clear()

    def _random_side(self, open_side: str) -> str:
        if self.rng.random() < self.cfg.open_side_prob:
            return open_side
        return "left" if open_side == "right" else "right"

    def _sticky(self) -> int:
        return _hold(self.rng, self.cfg.sticky_min_tics, self.cfg.sticky_max_tics)

    def _start_backward(self, open_side: str):
        turn = _chance(self.rng, self.cfg.backward_turn_share)
        self._start("backward_" + self._random_side(open_side) if turn else "backward", self._sticky())

    def _sample_action(self, open_side: str):
        cfg, rng = self.cfg, self.rng
        # stand last: with its weight 0, the draw picks what the version-2 walker's did
        w = np.array([cfg.forward_weight, cfg.curve_weight, cfg.turn_weight, cfg.backward_weight, cfg.stand_weight])
        kind = rng.choice(5, p=w / w.sum())
        if kind == 0:
            self._start("forward", _hold(rng, 20, 80))
        elif kind == 1:
            self._start("forward_" + self._random_side(open_side), _hold(rng, 8, 35))
        elif kind == 2:
            self._start(self._random_side(open_side), _hold(rng, 6, 30))
        elif kind == 3:
            self._start_backward(open_side)
        else:
            self._start("stand", self._sticky())

    def _start_use(self) -> tuple:
        """Stand for use_settle_tics, then press USE for use_hold_tics, alone (standing while a door opens) or
        pushing forward."""
        self.use_forward = not _chance(self.rng, self.cfg.use_alone_share)
        self._start("use", self.cfg.use_settle_tics + self.cfg.use_wait_tics)
        self.use_tics, self.since_use = self.cfg.use_hold_tics, 0
        return self._use_buttons()

    def _use_buttons(self) -> tuple:
        if self.hold > self.cfg.use_wait_tics:  # still in the first use_settle_tics of the USE's hold
            return _ACTIONS["stand"]
        pressing = self.use_tics > 0
        self.use_tics -= 1
        return (int(self.use_forward), 0, 0, 0, int(pressing))

    def _curve_away(self, open_side: str):
        """Curve away early, keeping the side once chosen so the walker does not zig-zag into the wall."""
        if self.action == "forward" or self.avoid_side is None:
            self.avoid_side = open_side
        if self.action != "forward_" + self.avoid_side:
            self._start("forward_" + self.avoid_side, _hold(self.rng, 6, 16))

    def _door_ahead(self) -> bool:
        """Sometimes take the wall ahead for a door: walk up to it to press USE (True when the walker does)."""
        if self.since_use > self.cfg.use_cooldown_tics and _chance(self.rng, self.cfg.door_use_prob):
            self._start("approach", self.cfg.approach_tics)
            return True
        return False

    def _stuck(self, xy) -> bool:
        if self.action not in _FORWARD_ACTIONS:
            return False
        self.forward_xy.append(xy)
        if len(self.forward_xy) < self.forward_xy.maxlen:
            return False
        (x0, y0), (x1, y1) = self.forward_xy[0], self.forward_xy[-1]
        return math.hypot(x1 - x0, y1 - y0) < self.cfg.stuck_distance

    def __call__(self, depth_HW: np.ndarray, xy) -> tuple:
        cfg, rng = self.cfg, self.rng
        ahead, open_side = self._depth_features(depth_HW)
        self.hold -= 1
        self.since_use += 1
        if self.action == "turn_around":
            self.back_tics = max(self.back_tics - 1, 0)  # backing away first, the turn held (the same angle in all)
            if self.hold <= 0:
                self._start("forward", _hold(rng, 20, 60))
        elif self.action == "use":
            # the walker stands, then holds USE, then keeps pushing (or standing) while a door (if any) opens
            if self.hold <= 0:
                self._start("forward", _hold(rng, 10, 30))
                return _ACTIONS["forward"]
            return self._use_buttons()
        elif self.action == "approach":
            if ahead <= cfg.door_depth or self.hold <= 0:  # close enough for USE to reach it
                return self._start_use()
        elif self.action == "avoid":
            if self.back_tics > 0:  # backing away first, the turn held; the view ahead only opens up
                self.back_tics -= 1
                return _ACTIONS["backward_" + self.avoid_side]
            # Keep turning until the view is open, not merely until the wall leaves the centre; after half a
            # turn without such a view, settle for less.
            self.spin_tics += 1
            needed = cfg.clear_depth if self.spin_tics * cfg.turn_speed < 180 else cfg.caution_depth
            if ahead >= needed:
                self._start("forward", _hold(rng, 20, 60))
            elif self.spin_tics > self.trapped_tics:  # walls all around: maybe a closed door
                return self._start_use()
        elif self._stuck(xy):
            if not self.just_used and rng.random() < cfg.use_prob:
                self.just_used = True
                return self._start_use()
            self.just_used = False
            self._start("turn_around", _hold(rng, *self.turn_around_tics))  # 100-180 degrees
            self.avoid_side = open_side
            if _chance(rng, cfg.avoid_backward_prob):
                self.back_tics = self._sticky()
        elif ahead < cfg.near_depth:
            if not self._door_ahead():
                self.avoid_side, self.spin_tics = open_side, 0
                self._start("avoid", 0)
                if _chance(rng, cfg.avoid_backward_prob):
                    self.back_tics = self._sticky()
        elif ahead < cfg.caution_depth and self.action in _FORWARD_ACTIONS:
            if not (self.action == "forward" and self._door_ahead()):
                self._curve_away(open_side)
        elif self.hold <= 0:
            reverse = self.action in _FORWARD_ACTIONS and _chance(rng, cfg.reverse_prob)
            self.avoid_side = None
            if reverse:  # shuttling: the forward walk turns straight into a backward one
                self._start_backward(open_side)
            else:
                self._sample_action(open_side)
        if self.action in ("turn_around", "avoid"):
            if self.back_tics > 0:
                return _ACTIONS["backward_" + self.avoid_side]
            return _ACTIONS[self.avoid_side]
        return _ACTIONS[self.action]


# what a map name may be, for the --train_maps help of the scripts that build worlds
MAP_NAMES_HELP = "MAPxx of freedoom2.wad, ExMy of freedoom1.wad (both bundled with ViZDoom)"


def is_episode_map(name: str) -> bool:
    """True for a Doom 1 style map name, ExMy (Freedoom: Phase 1), False for MAPxx (Freedoom: Phase 2)."""
    return len(name) == 4 and name[0] == "E" and name[2] == "M" and name[1].isdigit() and name[3].isdigit()


def wad_name(map_name: str) -> str:
    """The ViZDoom-bundled WAD holding `map_name`: freedoom1.wad for ExMy maps, freedoom2.wad for MAPxx."""
    return "freedoom1.wad" if is_episode_map(map_name) else "freedoom2.wad"


def _wad_path(map_name: str) -> str:
    import vizdoom as vzd  # imported here so `import sample_world.render` works without the optional dependency

    return os.path.join(os.path.dirname(vzd.__file__), wad_name(map_name))


def wad_maps(wad_path: str) -> list:
    """Names of the maps (MAPxx and ExMy lumps) in a Doom WAD file, read from its lump directory."""
    with open(wad_path, "rb") as f:
        magic, num_lumps, dir_offset = struct.unpack("<4sii", f.read(12))
        if magic not in (b"IWAD", b"PWAD"):
            raise ValueError(f"{wad_path}: not a Doom WAD file")
        f.seek(dir_offset)
        directory = f.read(16 * num_lumps)
    names = [directory[i + 8: i + 16].rstrip(b"\0").decode("ascii", "replace") for i in range(0, len(directory), 16)]
    return sorted(n for n in names if (len(n) == 5 and n.startswith("MAP") and n[3:].isdigit()) or is_episode_map(n))


def check_maps(maps: Sequence[str]):
    """Raise a clear error for a map that its WAD lacks (ViZDoom would hang on it): MAPxx names are looked up in
    freedoom2.wad, ExMy names in freedoom1.wad."""
    if not maps:
        raise ValueError("unknown map(s) (none given): name maps such as MAP01 (freedoom2.wad) or E1M1 (freedoom1.wad)")
    by_wad = {}
    for m in maps:
        by_wad.setdefault(_wad_path(m), []).append(m)
    problems = []
    for wad, names in sorted(by_wad.items()):
        known = wad_maps(wad)
        unknown = [m for m in names if m not in known]
        if unknown:
            problems.append(f"{unknown}: {wad} has {known[0]}..{known[-1]}")
    if problems:
        raise ValueError(f"unknown map(s) {'; '.join(problems)}")


def map_name(text: str) -> str:
    """argparse type of the map flags: a map its bundled WAD holds (check_maps), e.g. MAP01 or E1M1. Without ViZDoom
    installed only the form of the name is checked (a world that is already built needs no engine)."""
    try:
        wad = _wad_path(text)
    except ImportError:
        if is_episode_map(text) or (len(text) == 5 and text.startswith("MAP") and text[3:].isdigit()):
            return text
        raise argparse.ArgumentTypeError(f"unknown map {text!r}: name maps such as MAP01 (freedoom2.wad) or E1M1 "
                                         f"(freedoom1.wad)") from None
    known = wad_maps(wad)
    if text not in known:
        raise argparse.ArgumentTypeError(f"unknown map {text!r}: {wad_name(text)} has {known[0]}..{known[-1]}")
    return text


def make_game(map_name: str, cfg: WorldConfig, workdir: Optional[str] = None):
    """A headless ViZDoom game on `map_name` of a bundled WAD (`wad_name`): no monsters, HUD, weapon or sound.

    The engine writes _vizdoom.ini and a _vizdoom/ folder into its working directory: `workdir` (default: the
    current one) gives it a private one, so that engines started at the same moment do not race to create them.
    The engine is a process of its own that outlives a killed parent: the commands that start one make SIGTERM an
    orderly exit (common/shutdown.py), so that the caller's `game.close()` (a `finally`, DoomEnv's exit handler)
    still runs.
    """
    import vizdoom as vzd

    check_maps([map_name])
    game = vzd.DoomGame()
    if workdir is not None:
        game.set_doom_config_path(os.path.join(workdir, "_vizdoom.ini"))
    game.set_doom_game_path(_wad_path(map_name))
    game.set_doom_map(map_name)
    game.set_screen_resolution(vzd.ScreenResolution.RES_160X120)
    game.set_screen_format(vzd.ScreenFormat.RGB24)
    game.set_depth_buffer_enabled(True)
    game.set_render_hud(False)
    game.set_render_crosshair(False)
    game.set_render_weapon(False)
    game.set_render_messages(False)
    game.set_render_screen_flashes(False)
    game.set_window_visible(False)
    game.set_sound_enabled(False)
    game.set_mode(vzd.Mode.PLAYER)
    game.set_available_buttons(
        [vzd.Button.MOVE_FORWARD_BACKWARD_DELTA, vzd.Button.TURN_LEFT_RIGHT_DELTA, vzd.Button.USE])
    game.set_available_game_variables(
        [vzd.GameVariable.POSITION_X, vzd.GameVariable.POSITION_Y, vzd.GameVariable.ANGLE])
    game.set_episode_timeout(0)
    # -deathmatch: random spawn spot per episode seed (and no monsters); cheats allow god mode.
    game.add_game_args("-deathmatch -nomonsters +sv_cheats 1 +cl_showsecretmessage 0")
    cwd = os.getcwd()
    try:
        if workdir is not None:
            os.chdir(workdir)  # the engine process inherits it at init; nothing else runs meanwhile
        game.init()
    except Exception as e:  # ViZDoom raises its own types; name the map in the message
        raise RuntimeError(f"ViZDoom could not start map {map_name!r} of {wad_name(map_name)}: {e}") from e
    finally:
        os.chdir(cwd)
    return game


def gamma_table(gamma: float) -> list:
    """PIL point() table for RGB (3 x 256 entries) brightening dark tones: out = 255 * (in / 255) ** (1 / gamma)."""
    table = [round(255.0 * (i / 255.0) ** (1.0 / gamma)) for i in range(256)]
    return table * 3


def preprocess_frame(screen_HWC: np.ndarray, size: int, gamma_lut: list) -> np.ndarray:
    """Center-crop an (H, W, 3) uint8 screen to (H, H), resize to (size, size, 3) uint8 with an area filter and
    apply the gamma table."""
    H, W, _ = screen_HWC.shape
    x0 = (W - H) // 2
    crop = np.ascontiguousarray(screen_HWC[:, x0: x0 + H])
    return np.asarray(Image.fromarray(crop).resize((size, size), Image.Resampling.BOX).point(gamma_lut))


def driving_command(buttons_N5: np.ndarray, cfg: WorldConfig) -> np.ndarray:
    """The velocity held buttons command: (N, 5) 0/1 in BUTTON_NAMES order -> (N, 2) float32 (linear in map
    units/s, angular in rad/s counter-clockwise positive)."""
    b = np.asarray(buttons_N5, dtype=np.float64).reshape(-1, len(BUTTON_NAMES))
    linear = (b[:, 0] - b[:, 1]) * cfg.top_speed
    angular = (b[:, 2] - b[:, 3]) * cfg.turn_rate
    return np.stack([linear, angular], axis=1).astype(np.float32)


def measured_motion(poses_N3: np.ndarray, hz: float) -> np.ndarray:
    """(linear, angular) velocity from consecutive poses: (N+1, 3) [x, y, degrees] -> (N, 2) float32.

    Row t is the forward difference from pose t to pose t+1: displacement along the heading at t in map units/s,
    and heading change in rad/s (counter-clockwise positive).
    """
    poses = poses_N3.astype(np.float64)
    dxy = np.diff(poses[:, :2], axis=0)
    heading = np.deg2rad(poses[:-1, 2])
    linear = (dxy[:, 0] * np.cos(heading) + dxy[:, 1] * np.sin(heading)) * hz
    dtheta = (np.diff(poses[:, 2]) + 180.0) % 360.0 - 180.0
    angular = np.deg2rad(dtheta) * hz
    return np.stack([linear, angular], axis=1).astype(np.float32)


def engine_action(buttons, cfg: WorldConfig) -> list:
    """0/1 buttons in BUTTON_NAMES order -> ViZDoom inputs [forward speed, turn (degrees, right positive), use]."""
    forward, backward, left, right, use = buttons
    return [(forward - backward) * cfg.walk_speed, (right - left) * cfg.turn_speed, use]


def _is_cut(pose0, pose1, buttons, cfg: WorldConfig) -> bool:
    """True when pose0 -> pose1 is no walking step: a teleporter moved the player or set its heading."""
    step = math.hypot(pose1[0] - pose0[0], pose1[1] - pose0[1])
    turn = (pose1[2] - pose0[2] + 180.0) % 360.0 - 180.0
    expected_turn = (buttons[2] - buttons[3]) * cfg.turn_speed
    return step > MAX_STEP or abs(turn - expected_turn) > 1.0


def start_walk(game, seed: int, cfg: WorldConfig) -> ExplorerPolicy:
    """Start episode `seed` on an initialised game: engine seed, god mode and the unrecorded warm-up walk, as every
    recorded walk starts. Returns the explorer that walks on (its random stream continues the seed's)."""
    rng = np.random.default_rng(seed)
    game.set_seed(int(rng.integers(0, 2**31 - 1)))
    game.new_episode()
    game.send_game_command("god")
    policy = ExplorerPolicy(cfg, rng)
    for _ in range(int(rng.integers(cfg.warmup_min_tics, cfg.warmup_max_tics + 1))):
        if game.is_episode_finished():
            break
        state = game.get_state()
        game.make_action(engine_action(policy(state.depth_buffer, state.game_variables[:2]), cfg))
    return policy


def run_episode(game, episode_len: int, seed: int, cfg: WorldConfig) -> dict:
    """Play one episode on an initialised game.

    Returns frames (N, S, S, 3) uint8, buttons (N, 5) float32, driving_command and measured_motion (N, 2) float32
    and poses (N, 3) float32, with N = episode_len, or fewer when the level ends or a teleporter cuts the walk (the
    episode stops before the jump, so every measured motion is a real walking step).
    """
    policy = start_walk(game, seed, cfg)
    gamma_lut = gamma_table(cfg.gamma)
    frames, buttons_list, poses = [], [], []
    while not game.is_episode_finished():
        state = game.get_state()
        pose = tuple(float(v) for v in state.game_variables)
        if poses and _is_cut(poses[-1], pose, buttons_list[-1], cfg):
            break
        poses.append(pose)
        if len(frames) == episode_len:
            break
        buttons = policy(state.depth_buffer, pose[:2])
        frames.append(preprocess_frame(state.screen_buffer, cfg.frame_size, gamma_lut))
        buttons_list.append(buttons)
        game.make_action(engine_action(buttons, cfg))
    n = len(poses) - 1  # a frame needs the next pose for its measured motion
    poses_arr = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    buttons_arr = np.asarray(buttons_list[:n], dtype=np.float32).reshape(n, len(BUTTON_NAMES))
    return {
        "frames": np.asarray(frames[:n], dtype=np.uint8).reshape(n, cfg.frame_size, cfg.frame_size, 3),
        "buttons": buttons_arr,
        "driving_command": driving_command(buttons_arr, cfg),
        "measured_motion": measured_motion(poses_arr, HZ) if n > 0 else np.zeros((0, 2), np.float32),
        "poses": poses_arr[:n].astype(np.float32),
    }


def episode_seed(seed: int, split: str, map_name: str, episode: int, attempt: int = 0) -> int:
    """Seed of one episode attempt; distinct (split, map, episode, attempt) give independent streams, so the
    train and val splits never share an episode."""
    key = (zlib.crc32(split.encode()), zlib.crc32(map_name.encode()), episode, attempt)
    return int(np.random.SeedSequence(seed, spawn_key=key).generate_state(1)[0])


def is_good_episode(ep: dict, episode_len: int, cfg: WorldConfig) -> bool:
    """Reject walks cut short (level exit, teleporter) and walkers trapped in a closet (few 64-unit cells seen)."""
    n = len(ep["frames"])
    if n < cfg.min_episode_frac * episode_len:
        return False
    cells = len(np.unique(np.floor(ep["poses"][:, :2] / 64.0), axis=0))
    return cells * 1000 >= cfg.min_cells_per_1000_tics * n


def _run_task(task) -> list:
    """Worker entry point: (map, split, seed, episode indices, episode_len, cfg dict) -> list of episode dicts.

    Each episode tries seeds attempt 0, 1, ... until is_good_episode (keeping the last try after max_attempts).
    """
    map_name, split, seed, episodes, episode_len, cfg_dict = task
    cfg = WorldConfig(**cfg_dict)
    results = []
    with tempfile.TemporaryDirectory(prefix="vizdoom.", ignore_cleanup_errors=True) as workdir:
        game = make_game(map_name, cfg, workdir=workdir)
        try:
            for episode in episodes:
                for attempt in range(cfg.max_attempts):
                    ep_seed = episode_seed(seed, split, map_name, episode, attempt)
                    ep = run_episode(game, episode_len, ep_seed, cfg)
                    if is_good_episode(ep, episode_len, cfg):
                        break
                results.append({**ep, "seed": ep_seed})
        finally:
            game.close()
    return results


def map_in_order(fn, tasks: list, workers: int, stall_timeout_s: float = STALL_TIMEOUT_S):
    """Yield fn(task) for each task, in order, computed by `workers` processes.

    A worker that dies (a crash in the engine) or whose engine stops answering would leave multiprocessing's
    imap waiting forever. Here, when the next result takes longer than `stall_timeout_s`, the pool is killed and
    the tasks not yet yielded rerun in a fresh pool (a task's result depends only on its arguments); a second stall
    raises RuntimeError. Exceptions raised by fn propagate unchanged. On SIGTERM, as on Ctrl-C, the workers are
    stopped in order (when the command made SIGTERM an orderly exit, common/shutdown.py, the parent unwinds to the
    `finally` below): each closes its engine.
    """
    done = 0
    for attempt in range(2):
        # the default start method (fork on Linux: no re-import of `data`); each worker exits in order on SIGTERM
        pool = multiprocessing.Pool(workers, initializer=exit_on_sigterm)
        try:
            pending = [pool.apply_async(fn, (task,)) for task in tasks[done:]]
            for result in pending:
                value = result.get(timeout=stall_timeout_s)
                done += 1
                yield value
            return
        except multiprocessing.TimeoutError:
            if attempt == 1:
                raise RuntimeError(f"task {done + 1} of {len(tasks)} gave no result in {stall_timeout_s:.0f} s, "
                                   f"twice: a worker died or its ViZDoom engine hangs") from None
            print(f"WARNING: task {done + 1} of {len(tasks)} gave no result in {stall_timeout_s:.0f} s (a worker "
                  f"died or its engine hangs); restarting the workers for the {len(tasks) - done} tasks left",
                  file=sys.stderr)
        finally:
            stop_pool(pool)


def generate_split(maps: Sequence[str], episodes_per_map: int, episode_len: int, seed: int, *,
                   split: str = "train", workers: int = 1, cfg: Optional[WorldConfig] = None,
                   episodes_per_task: int = 6, progress: bool = True) -> dict:
    """Generate `episodes_per_map` episodes of `episode_len` tics on each map; episodes ordered map by map.

    Returns frames (N, S, S, 3) uint8, segment_ids (N,) int32 (episode index), actions_buttons (N, 5) float32,
    actions_driving_command and actions_measured_motion (N, 2) float32, poses (N, 3) float32, hz, maps (E,) per-episode map names,
    episode_seeds (E,) and button_names. The result depends only on the arguments (not on `workers`).
    """
    cfg = cfg or WorldConfig()
    if episodes_per_map < 1 or episode_len < 1 or workers < 1:
        raise ValueError(f"episodes_per_map, episode_len and workers must be >= 1, got {episodes_per_map}, "
                         f"{episode_len}, {workers}")
    check_maps(maps)
    episode_maps = [m for m in maps for _ in range(episodes_per_map)]
    tasks = [(m, split, seed, list(range(i, min(i + episodes_per_task, episodes_per_map))), episode_len,
              dataclasses.asdict(cfg)) for m in maps for i in range(0, episodes_per_map, episodes_per_task)]

    # Frames go straight into one preallocated buffer: the split may be several GB, so never hold it twice.
    frames = np.empty((len(episode_maps) * episode_len, cfg.frame_size, cfg.frame_size, 3), dtype=np.uint8)
    num_frames, episodes = 0, []
    results = map_in_order(_run_task, tasks, workers) if workers > 1 else map(_run_task, tasks)
    with tqdm(total=len(episode_maps), desc=f"sample world {split}", unit="episode", disable=not progress) as bar:
        for result in results:
            for ep in result:
                n = len(ep["frames"])
                frames[num_frames: num_frames + n] = ep.pop("frames")
                num_frames += n
                episodes.append(ep)
            bar.update(len(result))

    lengths = [len(ep["buttons"]) for ep in episodes]
    return {
        "frames": frames[:num_frames],
        "segment_ids": np.repeat(np.arange(len(episodes), dtype=np.int32), lengths),
        "actions_buttons": np.concatenate([ep["buttons"] for ep in episodes]),
        "actions_driving_command": np.concatenate([ep["driving_command"] for ep in episodes]),
        "actions_measured_motion": np.concatenate([ep["measured_motion"] for ep in episodes]),
        "poses": np.concatenate([ep["poses"] for ep in episodes]),
        "hz": np.int32(HZ),
        "maps": np.array(episode_maps),
        "episode_seeds": np.array([ep["seed"] for ep in episodes], dtype=np.uint32),
        "button_names": np.array(BUTTON_NAMES),
    }


def button_shares(buttons_N5: np.ndarray) -> dict:
    """(N, 5) 0/1 buttons in BUTTON_NAMES order -> the share of rows holding each button ("held"), and of the rows
    with no button, walking backward (with or without a turn), turning in place (a turn and no move), walking
    forward (with or without a turn or USE) and pressing USE; "rows": N."""
    b = np.asarray(buttons_N5).reshape(-1, len(BUTTON_NAMES)) > 0.5
    forward, backward, left, right, use = b.T
    n = len(b)

    def share(mask) -> float:
        return round(float(mask.mean()), 4) if n else 0.0

    return {"rows": n, "held": {name: share(b[:, i]) for i, name in enumerate(BUTTON_NAMES)},
            "no_button": share(~b.any(axis=1)), "backward": share(backward),
            "turn_in_place": share((left | right) & ~forward & ~backward), "forward": share(forward),
            "use": share(use)}


def button_stats(buttons_N5: np.ndarray, segment_ids: np.ndarray, step: int = STEP_TICS) -> dict:
    """The button shares of a split (button_shares), "per_tic" over every tic and "per_window_row" over every
    `step`-th tic of each walk (from its first): the rows a token dataset's window gives a model, so a press shorter
    than a step is mostly missed there."""
    segment_ids = np.asarray(segment_ids)
    index = np.arange(len(segment_ids))
    first = np.maximum.accumulate(np.where(np.r_[True, segment_ids[1:] != segment_ids[:-1]], index, 0))
    rows = (index - first) % step == 0
    return {"per_tic": button_shares(buttons_N5), "per_window_row": button_shares(np.asarray(buttons_N5)[rows])}


def _atomic_write(path: Path, write):
    """Call write(file object) on a temp file next to `path`, then rename it into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def save_split(path, data: dict):
    """Write a generate_split dict as an uncompressed .npz, atomically."""
    _atomic_write(Path(path), lambda f: np.savez(f, **data))


def _shares_line(shares: dict) -> str:
    return ", ".join(f"{k.replace('_', ' ')} {100 * shares[k]:.1f} %"
                     for k in ("forward", "backward", "turn_in_place", "no_button", "use"))


def build_sample_world(out_dir, seed: int = 0, train_maps: Sequence[str] = TRAIN_MAPS,
                       val_maps: Sequence[str] = VAL_MAPS, train_episodes: int = 10,
                       val_episodes: int = 1, episode_len: int = 2000, workers: int = 2,
                       overwrite: bool = False, cfg: Optional[WorldConfig] = None,
                       train_episode_len: Optional[int] = None) -> bool:
    """Write out_dir/train.npz, out_dir/val.npz and a JSON sidecar of the parameters.

    `train_episode_len` (default: `episode_len`) sets the training walks' length alone, so that a world with more,
    shorter training walks keeps the validation split of one with fewer, longer ones.
    Skips the work (returns False) when both files exist and the sidecar matches the requested parameters. The
    sidecar also records each split's button statistics (button_stats) under "button_stats", which the comparison
    leaves out.
    """
    cfg = cfg or WorldConfig()
    out_dir = Path(out_dir)
    params = {
        "generator_version": GENERATOR_VERSION, "seed": seed, "episode_len": episode_len, "hz": HZ,
        "button_names": list(BUTTON_NAMES), "config": dataclasses.asdict(cfg),
        "train": {"maps": list(train_maps), "episodes_per_map": train_episodes},
        "val": {"maps": list(val_maps), "episodes_per_map": val_episodes},
    }
    if train_episode_len is not None and train_episode_len != episode_len:
        # recorded only when it differs, so that the sidecars of worlds built before the option still match
        params["train"]["episode_len"] = train_episode_len
    sidecar = out_dir / SIDECAR_NAME
    outputs = [out_dir / "train.npz", out_dir / "val.npz"]
    if not overwrite and sidecar.exists() and all(p.exists() for p in outputs):
        try:
            old = json.loads(sidecar.read_text())
        except json.JSONDecodeError:
            old = None
        if isinstance(old, dict) and {k: v for k, v in old.items() if k != STATS_KEY} == params:
            print(f"{out_dir}: sample world already generated with these parameters; skipping")
            return False
        print(f"{out_dir}: parameters differ from {sidecar}; regenerating")
    sidecar.unlink(missing_ok=True)  # a partial rebuild must never look complete
    stats = {}
    for split, path in zip(("train", "val"), outputs):
        t0 = time.time()
        split_len = params[split].get("episode_len", episode_len)
        data = generate_split(params[split]["maps"], params[split]["episodes_per_map"], split_len, seed,
                              split=split, workers=workers, cfg=cfg)
        save_split(path, data)
        stats[split] = button_stats(data["actions_buttons"], data["segment_ids"])
        print(f"{path}: {len(data['frames'])} frames, {len(data['maps'])} episodes in {time.time() - t0:.1f}s; "
              f"buttons per window row: {_shares_line(stats[split]['per_window_row'])}")
    _atomic_write(sidecar, lambda f: f.write(json.dumps({**params, STATS_KEY: stats}, indent=2).encode()))
    return True


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    pass


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=_HelpFormatter)
    p.add_argument("--output_dir", default="data/sample/raw", help="directory for train.npz, val.npz and the sidecar")
    add_hidden_alias(p, "--out_dir", "output_dir")  # the spelling before train.py's was adopted
    p.add_argument("--seed", type=non_negative_int, default=0,
                   help="master seed; every episode's seed derives from it")
    p.add_argument("--train_maps", nargs="+", type=map_name, default=list(TRAIN_MAPS),
                   help=f"maps for training: {MAP_NAMES_HELP}")
    p.add_argument("--val_maps", nargs="+", type=map_name, default=list(VAL_MAPS),
                   help="maps for validation (held-out episodes on these maps; the default: the first 8 training "
                        "maps and the held-out map)")
    p.add_argument("--train_episodes", type=positive_int, default=10, help="training episodes per training map")
    p.add_argument("--val_episodes", type=positive_int, default=1, help="validation episodes per validation map")
    p.add_argument("--episode_len", type=positive_int, default=2000,
                   help="recorded tics (frames) per episode, 35 per second")
    p.add_argument("--train_episode_len", type=positive_int, default=None,
                   help="tics per training episode, if not --episode_len (validation keeps --episode_len)")
    p.add_argument("--workers", type=positive_int, default=2, help="processes generating episodes in parallel")
    p.add_argument("--overwrite", action="store_true", help="regenerate even if matching outputs exist")
    args = p.parse_args(argv)
    exit_on_sigterm()  # SIGTERM stops the workers and closes their engines, as Ctrl-C does
    build_sample_world(args.output_dir, seed=args.seed, train_maps=args.train_maps, val_maps=args.val_maps,
                       train_episodes=args.train_episodes, val_episodes=args.val_episodes,
                       episode_len=args.episode_len, workers=args.workers, overwrite=args.overwrite,
                       train_episode_len=args.train_episode_len)


if __name__ == "__main__":
    sys.exit(run_main("sample_world.render", main))
