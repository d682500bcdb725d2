"""How far the camera moved between two frames, from the pixels alone: an inverse-dynamics estimate that never reads
the actions, so a world model's imagined frames and the real ones are measured the same way.

`MotionNet`: two (64, 64, 3) frames one window step (15 tics) apart -> the camera's displacement in the first
frame's heading (forward and leftward, map units: a walker pressed against a wall slides along it) and its turn
(degrees, counter-clockwise positive), trained on the sample world's recorded frames and poses
(`train_motion_estimator`), each pair also played backwards (the motion of a walk reversed: backward steps and the
other turn, which the explorer rarely does), mirrored left to right and recoloured. The network is
antisymmetric by construction: a pair read backwards gives the opposite motion, so a frame paired with itself reads
exactly no motion (a policy that stands still is not seen drifting) and backward steps are read as well as forward
ones. `distance_from_start` dead-reckons a walk's frames into how far it ended from where it began.
"""
import json
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from common.errors import InputError
from sample_world.render import STEP_TICS

# what the saved weights mean: 2 is the antisymmetric network (1 read each pair once; its weights load but mean
# something else)
ESTIMATOR_VERSION = 2


class MotionNet(nn.Module):
    """(B, 64, 64, 3) frame pairs (before, after) uint8 -> (B, 3) normalized (forward, leftward, turn), the
    difference of one reading of (before, after) and one of (after, before)."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(6, 32, 4, stride=2, padding=1), nn.ReLU(), nn.Conv2d(32, 64, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(64, 64, 4, stride=2, padding=1), nn.ReLU(), nn.Flatten(), nn.Linear(64 * 8 * 8, 128),
            nn.ReLU(), nn.Linear(128, 3))
        self.register_buffer("scale", torch.ones(3))  # map units and degrees per normalized unit

    def read(self, first_BHW3: torch.Tensor, second_BHW3: torch.Tensor) -> torch.Tensor:
        x = torch.cat([first_BHW3, second_BHW3], dim=-1).permute(0, 3, 1, 2).float() / 127.5 - 1.0
        return self.net(x)

    def forward(self, before_BHW3: torch.Tensor, after_BHW3: torch.Tensor) -> torch.Tensor:
        return 0.5 * (self.read(before_BHW3, after_BHW3) - self.read(after_BHW3, before_BHW3))

    @torch.no_grad()
    def motion(self, frames_NHW3: np.ndarray) -> np.ndarray:
        """(N + 1) consecutive frames -> (N, 3) (forward, leftward map units, turn degrees) of each step."""
        f = torch.from_numpy(np.ascontiguousarray(frames_NHW3))
        return (self(f[:-1], f[1:]) * self.scale).numpy()


def pose_motion(pose_a_N3: np.ndarray, pose_b_N3: np.ndarray) -> np.ndarray:
    """Poses (x, y, heading degrees) -> (N, 3) the motion from a to b: displacement along a's heading and to its
    left, and the turn (degrees, wrapped to [-180, 180))."""
    a, b = pose_a_N3.astype(np.float64), pose_b_N3.astype(np.float64)
    d = b[:, :2] - a[:, :2]
    h = np.radians(a[:, 2])
    forward = d[:, 0] * np.cos(h) + d[:, 1] * np.sin(h)
    leftward = -d[:, 0] * np.sin(h) + d[:, 1] * np.cos(h)
    turn = (b[:, 2] - a[:, 2] + 180.0) % 360.0 - 180.0
    return np.stack([forward, leftward, turn], axis=1).astype(np.float32)


def step_pairs(poses_N3: np.ndarray, segment_ids: np.ndarray):
    """(first frames, second frames, motion (n, 3)) of every pair one step apart inside a walk, each both ways."""
    t = np.arange(len(poses_N3) - STEP_TICS)
    t = t[segment_ids[t] == segment_ids[t + STEP_TICS]]
    first, second = np.concatenate([t, t + STEP_TICS]), np.concatenate([t + STEP_TICS, t])
    return first, second, pose_motion(poses_N3[first], poses_N3[second])


def mirrored(before_BHW3: torch.Tensor, after_BHW3: torch.Tensor, goal_B3: torch.Tensor, flip_B: torch.Tensor):
    """The pairs where flip_B is set mirrored left to right, and their motion with it: forward stays, leftward and
    the turn change sign."""
    image = flip_B[:, None, None, None]
    sign = torch.where(flip_B[:, None], torch.tensor([1.0, -1.0, -1.0]), torch.ones(3))
    return (torch.where(image, before_BHW3.flip(2), before_BHW3), torch.where(image, after_BHW3.flip(2), after_BHW3),
            goal_B3 * sign)


def recoloured(before_BHW3: torch.Tensor, after_BHW3: torch.Tensor, rng: np.random.Generator):
    """Both frames of each pair in the same new colours: the channels shuffled, each scaled by 0.6-1.4, and a
    brightness offset of up to 30 levels (maps no split has use other textures and lights; motion is in the
    geometry, not the colours)."""
    batch = len(before_BHW3)
    order = torch.from_numpy(np.stack([rng.permutation(3) for _ in range(batch)]))
    gain = torch.from_numpy(rng.uniform(0.6, 1.4, (batch, 1, 1, 1, 3)).astype(np.float32))
    offset = torch.from_numpy(rng.uniform(-30.0, 30.0, (batch, 1, 1, 1, 1)).astype(np.float32))
    pair_B2HW3 = torch.stack([before_BHW3, after_BHW3], dim=1).float()
    pair_B2HW3 = torch.gather(pair_B2HW3, 4, order[:, None, None, None, :].expand_as(pair_B2HW3))
    pair_B2HW3 = (pair_B2HW3 * gain + offset).clamp(0, 255).round().to(torch.uint8)
    return pair_B2HW3[:, 0], pair_B2HW3[:, 1]


def train_motion_estimator(train_npz, out_path, steps: int = 8000, seed: int = 0, batch_size: int = 64,
                           progress: bool = True, device="cpu") -> MotionNet:
    """Fit MotionNet to the recorded walks of train_npz (frames, poses, segment_ids), every pair recoloured and half
    of them mirrored, the learning rate decaying to zero on a cosine; saved at out_path (.safetensors, and a .json
    of how). Trained on `device`, returned on the CPU."""
    from tqdm import tqdm

    with np.load(train_npz) as npz:
        frames, poses, segment_ids = npz["frames"], npz["poses"], npz["segment_ids"]
    first, second, target = step_pairs(poses, segment_ids)
    if not len(first):
        raise InputError(f"{train_npz}: no walk is longer than one step ({STEP_TICS} tics); the motion estimator "
                         f"learns from frames one step apart")
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = MotionNet()
    net.scale.copy_(torch.from_numpy(target.std(axis=0)).clamp(min=1e-3))
    target_t = torch.from_numpy(target) / net.scale
    net.to(device)
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: 0.5 * (1.0 + np.cos(np.pi * s / steps)))
    for _ in tqdm(range(steps), desc="motion estimator", disable=not progress):
        batch = rng.integers(len(first), size=batch_size)
        before, after, goal = mirrored(torch.from_numpy(frames[first[batch]]), torch.from_numpy(frames[second[batch]]),
                                       target_t[batch], torch.from_numpy(rng.random(batch_size) < 0.5))
        before, after = recoloured(before, after, rng)
        loss = nn.functional.smooth_l1_loss(net(before.to(device), after.to(device)), goal.to(device))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
    net.cpu()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.name}.tmp")
    save_file(net.state_dict(), str(tmp))
    tmp.replace(out_path)
    out_path.with_suffix(".json").write_text(json.dumps({"train_data": str(train_npz), "steps": steps, "seed": seed,
                                                        "batch_size": batch_size, "version": ESTIMATOR_VERSION}))
    return net.eval()


def version_mismatch(path) -> Optional[str]:
    """Why the estimator at path (.safetensors, its record the .json beside it) is not this version's network,
    None when it is."""
    from sample_world.policies import read_record

    record_path = Path(path).with_suffix(".json")
    record = read_record(record_path)
    if record is None:
        return f"{record_path} is missing or unreadable"
    version = record.get("version", 1)
    if version != ESTIMATOR_VERSION:
        return (f"{path} is a motion estimator of version {version}, this version reads pairs with version "
                f"{ESTIMATOR_VERSION}'s network")
    return None


def load_motion_estimator(path) -> MotionNet:
    """The estimator trained into path; an InputError when it is missing or of another version (the policies
    protocol retrains it: ./evaluate.py --protocol policies)."""
    reason = version_mismatch(path) if Path(path).is_file() else f"{path} is not there"
    if reason:
        raise InputError(f"{reason}; ./evaluate.py --protocol policies trains it (or delete it to have it retrained)")
    net = MotionNet()
    net.load_state_dict(load_file(str(path)))
    return net.eval()


def dead_reckon(steps_N3: Sequence) -> np.ndarray:
    """(N, 3) (forward, leftward, turn degrees) per step, each in the heading the step starts with -> (N + 1, 2)
    positions from (0, 0), heading 0 at the start. Rows of 2 (forward, turn) have no sideways part."""
    steps = np.asarray(steps_N3, dtype=np.float64)
    steps = steps.reshape(-1, steps.shape[-1]) if steps.size else np.zeros((0, 3))
    if steps.shape[1] == 2:
        steps = np.stack([steps[:, 0], np.zeros(len(steps)), steps[:, 1]], axis=1)
    position, heading, path = np.zeros(2), 0.0, [np.zeros(2)]
    for forward, leftward, turn in steps:
        c, s = np.cos(heading), np.sin(heading)
        position = position + forward * np.array([c, s]) + leftward * np.array([-s, c])
        heading += np.radians(turn)
        path.append(position)
    return np.stack(path)


def distance_from_start(steps_N3: Sequence) -> float:
    """How far from the start a walk of these step motions ends, in map units."""
    return float(np.linalg.norm(dead_reckon(steps_N3)[-1]))
