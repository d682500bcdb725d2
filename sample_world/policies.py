"""Policies that drive the sample world (or a world model of it) from what a camera sees.

A policy is any object with `reset(seed)` (an episode starts) and `act(frame)`: the latest (64, 64, 3) uint8 RGB
frame -> the list of buttons to hold for the next window step (names of sample_world.render.BUTTON_NAMES). It sees
nothing else: no depth, pose or map. `load_policy(spec)` gives one from a built-in name or from
`path/to/file.py:ClassName` (constructed without arguments).

The built-in suite (`BUILTIN_POLICIES`) spans what policies do: scripted ones that get nowhere or get stuck (turning
in place, shuttling forward and back, random buttons, always forward, always backward, standing, dithering between
forward and backward), two that steer by the pixels (toward the darker, deeper side; along a wall on the right) and
policies behaviour-cloned from the walker's recorded frames and buttons (`BCNet`, a small CNN over the macro actions
the explorer holds) at three training budgets, the best of them mixed with random actions at two rates. The cloned
weights are trained on first use (`train_bc_policies`) into a policy folder, about a minute on a CPU, with a record
of what they were trained from (bc_policies.json: the macro actions and the training data's fingerprint);
`stale_reason` says when weights in a policy folder cannot be reused for some training data, and the policies
protocol then retrains them.
"""
import hashlib
import importlib.util
import json
import logging
import zipfile
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from common.errors import InputError
from sample_world.render import BUTTON_NAMES, SIDECAR_NAME, STEP_TICS, ButtonsError, buttons_from_names

logger = logging.getLogger(__name__)
# The macro actions a cloned policy chooses between: every combination of buttons the version-3 walker holds
# (sample_world/render.py). A recorded tic holding any other combination is labelled UNMATCHED (macro_ids).
MACRO_BUTTONS = {
    "none": (), "forward": ("MOVE_FORWARD",), "forward_left": ("MOVE_FORWARD", "TURN_LEFT"),
    "forward_right": ("MOVE_FORWARD", "TURN_RIGHT"), "left": ("TURN_LEFT",), "right": ("TURN_RIGHT",),
    "backward": ("MOVE_BACKWARD",), "backward_left": ("MOVE_BACKWARD", "TURN_LEFT"),
    "backward_right": ("MOVE_BACKWARD", "TURN_RIGHT"), "use": ("USE",), "use_forward": ("MOVE_FORWARD", "USE"),
}
MACRO_NAMES = tuple(MACRO_BUTTONS)
MACROS = tuple(MACRO_BUTTONS.values())  # a cloned policy's output k holds MACROS[k]
UNMATCHED = -1  # macro_ids' label of a tic whose buttons are no macro's
BC_RECORD = "bc_policies.json"
BC_BUDGETS = {"bc_small": 15, "bc_medium": 150, "bc_large": 1500}  # training steps of batch 64
BUILTIN_POLICIES = ("spin", "shuttle", "random", "forward", "backward", "stand", "dither", "dark_seeker", "wall_hugger",
                    "bc_small", "bc_medium", "bc_large", "bc_large_random50", "bc_large_random25")


class PolicyError(InputError):
    """A policy that does not load, or an action that names no button."""


def check_action(action, name: str) -> np.ndarray:
    """A policy's answer -> the held buttons as a 0/1 vector in BUTTON_NAMES order; clear error for anything
    else."""
    try:
        return buttons_from_names(action)
    except ButtonsError as e:
        raise PolicyError(f"policy {name}: act() returned no buttons it could hold: {e}") from None


class Memoryless:
    """A policy whose action depends on the frame alone: nothing to reset."""

    def reset(self, seed: int) -> None:
        pass


class HoldButtons(Memoryless):
    """Holds the same buttons every step, whatever it sees (`BUTTONS`)."""
    BUTTONS: Tuple[str, ...] = ()

    def act(self, frame: np.ndarray) -> List[str]:
        return list(self.BUTTONS)


class Spin(HoldButtons):
    """Turns left in place: sees the room, goes nowhere."""
    BUTTONS = ("TURN_LEFT",)


class AlwaysForward(HoldButtons):
    """Walks straight ahead until a wall stops it."""
    BUTTONS = ("MOVE_FORWARD",)


class AlwaysBackward(HoldButtons):
    """Walks backward until a wall behind it stops it: as far as forward on open ground, with nothing seen ahead."""
    BUTTONS = ("MOVE_BACKWARD",)


class Stand(HoldButtons):
    """Holds no button: stays where it is (a coasting start drifts a little)."""


class Shuttle:
    """Two steps forward, two steps back: a long path that ends where it began."""

    def reset(self, seed: int) -> None:
        self.t = 0

    def act(self, frame: np.ndarray) -> List[str]:
        self.t += 1
        return ["MOVE_FORWARD"] if (self.t - 1) % 4 < 2 else ["MOVE_BACKWARD"]


class Dither:
    """Forward or backward at random each step: a long path that wanders little from its start."""

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, frame: np.ndarray) -> List[str]:
        return ["MOVE_FORWARD"] if self.rng.random() < 0.5 else ["MOVE_BACKWARD"]


BRIGHTNESS_MARGIN = 4.0  # brightness levels (of 255) that the pixel-steering policies call a difference


def _band_brightness(frame: np.ndarray) -> tuple:
    """Mean brightness of the left, centre and right thirds of the frame's middle band (rows 21-42 of 64). Light
    fades with distance in this world: over the explorer's walks, the darker side is the deeper one (correlation
    -0.72 between the sides' brightness and depth differences)."""
    band = frame[frame.shape[0] // 3: 2 * frame.shape[0] // 3].astype(np.float32).mean(-1)
    third = band.shape[1] // 3
    return band[:, :third].mean(), band[:, third:-third].mean(), band[:, -third:].mean()


class DarkSeeker(Memoryless):
    """Turns on what it sees: walks toward the darker (deeper) side of the view, and turns in place toward it when
    the centre is clearly brighter (a wall close ahead)."""

    def act(self, frame: np.ndarray) -> List[str]:
        left, centre, right = _band_brightness(frame)
        turn = "TURN_LEFT" if left < right else "TURN_RIGHT"
        if centre > min(left, right) + BRIGHTNESS_MARGIN:
            return [turn]
        return ["MOVE_FORWARD", turn] if abs(left - right) > BRIGHTNESS_MARGIN else ["MOVE_FORWARD"]


class WallHugger(Memoryless):
    """Keeps a wall on its right, from the pixels: turns left when the view ahead is a close (bright) wall, bears
    right when the right side opens up (darker than the centre), else walks on."""

    def act(self, frame: np.ndarray) -> List[str]:
        left, centre, right = _band_brightness(frame)
        if centre > max(left, right) + BRIGHTNESS_MARGIN:
            return ["TURN_LEFT"]
        if right + BRIGHTNESS_MARGIN < centre:
            return ["MOVE_FORWARD", "TURN_RIGHT"]
        return ["MOVE_FORWARD"]


class RandomButtons:
    """One of the macro actions, uniformly at random each step."""

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def act(self, frame: np.ndarray) -> List[str]:
        return list(MACROS[int(self.rng.integers(len(MACROS)))])


class BCNet(nn.Module):
    """(B, 64, 64, 3) uint8 frames -> (B, len(MACROS)) logits of the macro action to hold next."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, 16, 4, stride=2, padding=1), nn.ReLU(), nn.Conv2d(16, 32, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2, padding=1), nn.ReLU(), nn.Flatten(), nn.Linear(64 * 8 * 8, 128),
            nn.ReLU(), nn.Linear(128, len(MACROS)))

    def forward(self, frames_BHW3: torch.Tensor) -> torch.Tensor:
        x = frames_BHW3.permute(0, 3, 1, 2).float() / 127.5 - 1.0
        return self.net(x)


def load_bc_net(weights) -> BCNet:
    """A BCNet from a .safetensors file; a clear PolicyError (no stack trace) when the file does not load or its
    tensors are not this BCNet's (e.g. cloned over another set of macro actions)."""
    net = BCNet()
    try:
        state = load_file(str(weights))
    except Exception as e:  # a truncated or foreign file: name it and the error in one line
        raise PolicyError(f"{weights} does not load as a cloned policy: {type(e).__name__}: {e}") from None
    want = {k: tuple(v.shape) for k, v in net.state_dict().items()}
    got = {k: tuple(v.shape) for k, v in state.items()}
    if got != want:
        out = got.get(list(want)[-1], ("?",))[0]  # the last layer's bias: one per macro action
        raise PolicyError(f"{weights}: not a cloned policy of this version ({out} macro outputs, this version "
                          f"has {len(MACROS)}: {', '.join(MACRO_NAMES)}); retrain it (train_bc_policies, which "
                          f"./evaluate.py --protocol policies runs when the record does not match)")
    net.load_state_dict(state)
    return net.eval()


class BehaviourCloned:
    """Draws the macro action from a BCNet's distribution; with `random_rate`, a uniformly random one instead."""

    def __init__(self, weights: Path, random_rate: float = 0.0):
        self.net = load_bc_net(weights)
        self.random_rate = random_rate

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    @torch.no_grad()
    def act(self, frame: np.ndarray) -> List[str]:
        if self.random_rate and self.rng.random() < self.random_rate:
            return list(MACROS[int(self.rng.integers(len(MACROS)))])
        probs = self.net(torch.from_numpy(np.ascontiguousarray(frame))[None]).softmax(-1)[0].double().numpy()
        return list(MACROS[int(self.rng.choice(len(MACROS), p=probs / probs.sum()))])


def macro_ids(buttons_N5: np.ndarray) -> np.ndarray:
    """(N, 5) held buttons per tic (0/1, BUTTON_NAMES order) -> (N,) the index in MACROS of the macro holding exactly
    those buttons, UNMATCHED (-1) for a row that is no macro's (e.g. forward and backward at once, or not 0/1)."""
    buttons_N5 = np.asarray(buttons_N5)
    if buttons_N5.ndim != 2 or buttons_N5.shape[1] != len(BUTTON_NAMES):
        raise PolicyError(f"button rows must be (N, {len(BUTTON_NAMES)}) in {list(BUTTON_NAMES)} order, got shape "
                          f"{buttons_N5.shape}")
    table_M5 = np.stack([buttons_from_names(m) for m in MACROS])
    same_NM = (buttons_N5[:, None, :] == table_M5[None]).all(-1)  # a row matches one macro at most
    return np.where(same_NM.any(1), same_NM.argmax(1), UNMATCHED)


def macro_targets(buttons_N5: np.ndarray, segment_ids: np.ndarray) -> tuple:
    """(frame indices, macro ids): for each frame with a whole window step after it in its walk, the macro action
    held for most of the next 15 tics (ties: the first in MACROS). Tics that are no macro's (macro_ids) are not
    relabelled: a step where they outnumber every macro is skipped, since it is no macro the policy could hold."""
    n = len(buttons_N5)
    starts = np.arange(n - STEP_TICS + 1)
    starts = starts[segment_ids[starts] == segment_ids[starts + STEP_TICS - 1]]
    windows = macro_ids(buttons_N5)[starts[:, None] + np.arange(STEP_TICS)]
    counts = np.stack([(windows == k).sum(1) for k in range(len(MACROS))], axis=1)
    clear = counts.max(1) > (windows == UNMATCHED).sum(1)
    return starts[clear], counts.argmax(1)[clear]


def data_source(train_npz) -> dict:
    """What a training .npz is, cheaply (no pass over its bytes): its sidecar's generator_version (None without a
    sidecar) and a fingerprint of its arrays' names, sizes and CRC-32s, which the .npz's zip directory holds."""
    train_npz = Path(train_npz)
    try:
        with zipfile.ZipFile(train_npz) as z:
            members = sorted((i.filename, i.file_size, i.CRC) for i in z.infolist())
    except (OSError, zipfile.BadZipFile) as e:
        raise PolicyError(f"{train_npz}: not a readable .npz of recorded walks ({e})") from None
    sidecar = train_npz.parent / SIDECAR_NAME
    try:
        version = json.loads(sidecar.read_text()).get("generator_version") if sidecar.is_file() else None
    except (json.JSONDecodeError, AttributeError):
        version = None
    fingerprint = hashlib.sha256(json.dumps(members).encode()).hexdigest()[:16]
    return {"train_data": str(train_npz), "generator_version": version, "fingerprint": fingerprint}


def describe_source(source: dict) -> str:
    return (f"{source.get('train_data')} (generator version {source.get('generator_version')}, fingerprint "
            f"{source.get('fingerprint')})")


def read_record(path) -> Optional[dict]:
    """The JSON record beside some weights, None when it is missing or unreadable."""
    try:
        record = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return record if isinstance(record, dict) else None


def macros_mismatch(record_path) -> Optional[str]:
    """Why the cloned policies recorded at record_path (BC_RECORD) do not choose between this version's MACROS,
    None when they do."""
    macros = (read_record(record_path) or {}).get("macros")
    if macros == [list(m) for m in MACROS]:
        return None
    if not isinstance(macros, list):
        return f"{record_path} does not record the macro actions they choose between"
    return (f"{record_path}: cloned over {len(macros)} other macro actions than this version's {len(MACROS)} "
            f"({', '.join(MACRO_NAMES)})")


def stale_reason(weights: Sequence[Path], record_path: Path, train_npz, check_macros: bool) -> Optional[str]:
    """Why the cached `weights` (with their record at record_path) cannot be reused for a model of train_npz, None
    when they can: a file missing, no record of the training data, other macro actions (check_macros, for the
    cloned policies), or other training data. Without train_npz on disk the data goes unchecked (a warning)."""
    missing = [str(p) for p in weights if not Path(p).is_file()]
    if missing:
        return f"{missing[0]} is not there"
    reason = macros_mismatch(record_path) if check_macros else None
    if reason:
        return reason
    source = (read_record(record_path) or {}).get("source")
    if not isinstance(source, dict):
        return f"{record_path} does not record the training data's fingerprint (trained by an older version)"
    if not Path(train_npz).is_file():
        logger.warning("%s not found: using %s as trained from %s, unchecked", train_npz, record_path.parent,
                       describe_source(source))
        return None
    now = data_source(train_npz)
    if source.get("fingerprint") != now["fingerprint"]:
        return f"trained from {describe_source(source)}; the training data is now {describe_source(now)}"
    return None


def stamp_source(record_path, train_npz) -> None:
    """Add the training data's data_source to the JSON record at record_path (created when missing)."""
    record_path = Path(record_path)
    record = read_record(record_path) or {}
    record["source"] = data_source(train_npz)
    record_path.write_text(json.dumps(record, indent=2))


def train_bc_policies(train_npz, policy_dir, seed: int = 0, progress: bool = True) -> None:
    """Behaviour-clone the recorded walker at each of BC_BUDGETS' step counts into policy_dir/<name>.safetensors
    (one run, saved as it passes each budget), then the record (BC_RECORD): the macro actions and the training
    data's data_source, written last so that an interrupted run leaves none."""
    from tqdm import tqdm

    policy_dir = Path(policy_dir)
    policy_dir.mkdir(parents=True, exist_ok=True)
    source = data_source(train_npz)
    (policy_dir / BC_RECORD).unlink(missing_ok=True)  # weights half replaced must not pass for either run's
    with np.load(train_npz) as npz:
        frames, buttons, segment_ids = npz["frames"], npz["actions_buttons"], npz["segment_ids"]
    unmatched = float((macro_ids(buttons) == UNMATCHED).mean())
    if unmatched:
        logger.warning("%s: %.2f %% of the tics hold buttons that are no macro action's; steps mostly of them are "
                       "skipped", train_npz, 100 * unmatched)
    index, target = macro_targets(buttons, segment_ids)
    if not len(index):
        raise PolicyError(f"{train_npz}: no window step of the recorded walks holds a macro action to clone")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = BCNet()
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    budgets = sorted(BC_BUDGETS.items(), key=lambda kv: kv[1])
    for step in tqdm(range(1, budgets[-1][1] + 1), desc="behaviour cloning", disable=not progress):
        batch = rng.integers(len(index), size=64)
        loss = nn.functional.cross_entropy(net(torch.from_numpy(frames[index[batch]])),
                                           torch.from_numpy(target[batch]))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        for name, budget in budgets:
            if step == budget:
                tmp = policy_dir / f".{name}.tmp"
                save_file(net.state_dict(), str(tmp))
                tmp.replace(policy_dir / f"{name}.safetensors")
    record = {"train_data": str(train_npz), "budgets": BC_BUDGETS, "seed": seed, "macro_names": MACRO_NAMES,
              "macros": MACROS, "unmatched_tic_share": unmatched, "source": source}
    (policy_dir / BC_RECORD).write_text(json.dumps(record, indent=2))


def bc_weights(policy_dir) -> List[Path]:
    """The cloned policies' weight files in policy_dir, one per BC_BUDGETS entry."""
    return [Path(policy_dir) / f"{name}.safetensors" for name in BC_BUDGETS]


def builtin_policy(name: str, policy_dir: Path):
    scripted = {"spin": Spin, "shuttle": Shuttle, "random": RandomButtons, "forward": AlwaysForward,
                "backward": AlwaysBackward, "stand": Stand, "dither": Dither, "dark_seeker": DarkSeeker,
                "wall_hugger": WallHugger}
    if name in scripted:
        return scripted[name]()
    base, _, rate = name.partition("_random")
    weights = Path(policy_dir) / f"{base}.safetensors"
    if base not in BC_BUDGETS or (rate and not rate.isdigit()):
        raise PolicyError(f"unknown policy {name!r}: the built-in ones are {list(BUILTIN_POLICIES)} (or give "
                          f"path/to/file.py:ClassName)")
    if not weights.is_file():
        raise PolicyError(f"{weights} not found: train the cloned policies first (train_bc_policies)")
    reason = macros_mismatch(weights.parent / BC_RECORD)
    if reason:
        raise PolicyError(f"{name}: {reason}; retrain the cloned policies (train_bc_policies, which "
                          f"./evaluate.py --protocol policies runs when they do not match)")
    return BehaviourCloned(weights, int(rate) / 100 if rate else 0.0)


def load_policy(spec: str, policy_dir: Optional[Path] = None):
    """A built-in policy by name, or `path/to/file.py:ClassName` constructed without arguments."""
    if ":" not in spec:
        return builtin_policy(spec, Path(policy_dir or "data/policies"))
    path, _, class_name = spec.rpartition(":")
    if not Path(path).is_file():
        raise PolicyError(f"policy {spec}: {path} not found (give path/to/file.py:ClassName or a built-in name)")
    try:
        module_spec = importlib.util.spec_from_file_location(f"policy_{Path(path).stem}", path)
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
        policy = getattr(module, class_name)()
    except Exception as e:  # whatever the user's file raises: name the file and the error in one line
        raise PolicyError(f"policy {spec} does not load: {type(e).__name__}: {e}") from None
    for method in ("reset", "act"):
        if not callable(getattr(policy, method, None)):
            raise PolicyError(f"policy {spec}: {class_name} has no {method}() method")
    return policy


def load_policies(specs: Sequence[str], policy_dir: Path) -> Dict[str, object]:
    names = [s.rpartition(":")[2] if ":" in s else s for s in specs]
    if len(set(names)) != len(names):
        raise PolicyError(f"policy names must differ, got {names}")
    return {name: load_policy(spec, policy_dir) for name, spec in zip(names, specs)}
