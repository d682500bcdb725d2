"""Policies that drive the sample world (or a world model of it) from what a camera sees.

A policy is any object with `reset(seed)` (an episode starts) and `act(frame)`: the latest (64, 64, 3) uint8 RGB
frame -> the list of buttons to hold for the next window step (names of sample_world.render.BUTTON_NAMES). It sees
nothing else: no depth, pose or map. `load_policy(spec)` gives one from a built-in name or from
`path/to/file.py:ClassName` (constructed without arguments).

The built-in suite (`BUILTIN_POLICIES`) is graded: scripted ones that get nowhere or get stuck (turning in place,
shuttling forward and back, random buttons, always forward) and policies behaviour-cloned from the walker's recorded
frames and buttons (`BCNet`, a small CNN over the macro actions the explorer holds) at three training budgets, the
best of them mixed with random actions at two rates. The cloned weights are trained on first use
(`train_bc_policies`) into a policy folder, about a minute on a CPU.
"""
import importlib.util
import json
from pathlib import Path
from typing import Dict, List, Optional, Sequence

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from common.errors import InputError
from sample_world.render import BUTTON_NAMES, STEP_TICS, ButtonsError, buttons_from_names
# the macro actions a cloned policy chooses between (held buttons), the explorer's own plus standing still
MACROS = ((), ("MOVE_FORWARD",), ("MOVE_FORWARD", "TURN_LEFT"), ("MOVE_FORWARD", "TURN_RIGHT"), ("TURN_LEFT",),
          ("TURN_RIGHT",), ("MOVE_BACKWARD",), ("MOVE_FORWARD", "USE"))
BC_BUDGETS = {"bc_small": 15, "bc_medium": 150, "bc_large": 1500}  # training steps of batch 64
BUILTIN_POLICIES = ("spin", "shuttle", "random", "forward", "bc_small", "bc_medium", "bc_large", "bc_large_random50",
                    "bc_large_random25")


class PolicyError(InputError):
    """A policy that does not load, or an action that names no button."""


def check_action(action, name: str) -> np.ndarray:
    """A policy's answer -> the held buttons as a 0/1 vector in BUTTON_NAMES order; clear error for anything
    else."""
    try:
        return buttons_from_names(action)
    except ButtonsError as e:
        raise PolicyError(f"policy {name}: act() returned no buttons it could hold: {e}") from None


class Spin:
    """Turns left in place: sees the room, goes nowhere."""

    def reset(self, seed: int) -> None:
        pass

    def act(self, frame: np.ndarray) -> List[str]:
        return ["TURN_LEFT"]


class AlwaysForward:
    """Walks straight ahead until a wall stops it."""

    def reset(self, seed: int) -> None:
        pass

    def act(self, frame: np.ndarray) -> List[str]:
        return ["MOVE_FORWARD"]


class Shuttle:
    """Two steps forward, two steps back: a long path that ends where it began."""

    def reset(self, seed: int) -> None:
        self.t = 0

    def act(self, frame: np.ndarray) -> List[str]:
        self.t += 1
        return ["MOVE_FORWARD"] if (self.t - 1) % 4 < 2 else ["MOVE_BACKWARD"]


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


class BehaviourCloned:
    """Draws the macro action from a BCNet's distribution; with `random_rate`, a uniformly random one instead."""

    def __init__(self, weights: Path, random_rate: float = 0.0):
        self.net = BCNet().eval()
        self.net.load_state_dict(load_file(str(weights)))
        self.random_rate = random_rate

    def reset(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    @torch.no_grad()
    def act(self, frame: np.ndarray) -> List[str]:
        if self.random_rate and self.rng.random() < self.random_rate:
            return list(MACROS[int(self.rng.integers(len(MACROS)))])
        probs = self.net(torch.from_numpy(np.ascontiguousarray(frame))[None]).softmax(-1)[0].double().numpy()
        return list(MACROS[int(self.rng.choice(len(MACROS), p=probs / probs.sum()))])


def macro_targets(buttons_N5: np.ndarray, segment_ids: np.ndarray) -> tuple:
    """(frame indices, macro ids): for each frame with a whole window step after it in its walk, the macro action
    held for most of the next 15 tics."""
    n = len(buttons_N5)
    starts = np.arange(n - STEP_TICS + 1)
    starts = starts[segment_ids[starts] == segment_ids[starts + STEP_TICS - 1]]
    codes = {tuple(int(b in m) for b in BUTTON_NAMES): i for i, m in enumerate(MACROS)}
    per_tic = np.array([codes.get(tuple(int(v) for v in row), 0) for row in buttons_N5.astype(np.int64)])
    windows = per_tic[starts[:, None] + np.arange(STEP_TICS)]
    counts = np.stack([(windows == k).sum(1) for k in range(len(MACROS))], axis=1)
    return starts, counts.argmax(1)


def train_bc_policies(train_npz, policy_dir, seed: int = 0, progress: bool = True) -> None:
    """Behaviour-clone the recorded walker at each of BC_BUDGETS' step counts into policy_dir/<name>.safetensors
    (one run, saved as it passes each budget)."""
    from tqdm import tqdm

    policy_dir = Path(policy_dir)
    policy_dir.mkdir(parents=True, exist_ok=True)
    with np.load(train_npz) as npz:
        frames, buttons, segment_ids = npz["frames"], npz["actions_buttons"], npz["segment_ids"]
    index, target = macro_targets(buttons, segment_ids)
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
    (policy_dir / "bc_policies.json").write_text(json.dumps({"train_data": str(train_npz), "budgets": BC_BUDGETS,
                                                             "seed": seed, "macros": MACROS}, indent=2))


def builtin_policy(name: str, policy_dir: Path):
    scripted = {"spin": Spin, "shuttle": Shuttle, "random": RandomButtons, "forward": AlwaysForward}
    if name in scripted:
        return scripted[name]()
    base, _, rate = name.partition("_random")
    weights = Path(policy_dir) / f"{base}.safetensors"
    if base not in BC_BUDGETS or (rate and not rate.isdigit()):
        raise PolicyError(f"unknown policy {name!r}: the built-in ones are {list(BUILTIN_POLICIES)} (or give "
                          f"path/to/file.py:ClassName)")
    if not weights.is_file():
        raise PolicyError(f"{weights} not found: train the cloned policies first (train_bc_policies)")
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
