"""How far the camera moved between two frames, from the pixels alone: an inverse-dynamics estimate that never reads
the actions, so a world model's imagined frames and the real ones are measured the same way.

`MotionNet`: two (64, 64, 3) frames one window step (15 tics) apart -> the camera's displacement in the first
frame's heading (forward and leftward, map units: a walker pressed against a wall slides along it) and its turn
(degrees, counter-clockwise positive), trained on the sample world's recorded frames and poses
(`train_motion_estimator`), each pair also played backwards (the motion of a walk reversed: backward steps and the
other turn, which the explorer rarely does) and a share of still pairs. `distance_from_start` dead-reckons a walk's
frames into how far it ended from where it began.
"""
import json
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

from sample_world.render import STEP_TICS


class MotionNet(nn.Module):
    """(B, 64, 64, 3) frame pairs (before, after) uint8 -> (B, 3) normalized (forward, leftward, turn)."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(6, 32, 4, stride=2, padding=1), nn.ReLU(), nn.Conv2d(32, 64, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(64, 64, 4, stride=2, padding=1), nn.ReLU(), nn.Flatten(), nn.Linear(64 * 8 * 8, 128),
            nn.ReLU(), nn.Linear(128, 3))
        self.register_buffer("scale", torch.ones(3))  # map units and degrees per normalized unit

    def forward(self, before_BHW3: torch.Tensor, after_BHW3: torch.Tensor) -> torch.Tensor:
        x = torch.cat([before_BHW3, after_BHW3], dim=-1).permute(0, 3, 1, 2).float() / 127.5 - 1.0
        return self.net(x)

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


def train_motion_estimator(train_npz, out_path, steps: int = 2000, seed: int = 0, still_share: float = 0.1,
                           progress: bool = True) -> MotionNet:
    """Fit MotionNet to the recorded walks of train_npz (frames, poses, segment_ids), `still_share` of each batch
    a frame paired with itself (no motion); saved at out_path (.safetensors, and a .json of how)."""
    from tqdm import tqdm

    with np.load(train_npz) as npz:
        frames, poses, segment_ids = npz["frames"], npz["poses"], npz["segment_ids"]
    first, second, target = step_pairs(poses, segment_ids)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = MotionNet()
    net.scale.copy_(torch.from_numpy(target.std(axis=0)).clamp(min=1e-3))
    target_t = torch.from_numpy(target) / net.scale
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in tqdm(range(steps), desc="motion estimator", disable=not progress):
        batch = rng.integers(len(first), size=64)
        still = rng.random(64) < still_share
        a, b = first[batch], np.where(still, first[batch], second[batch])
        goal = torch.where(torch.from_numpy(still)[:, None], 0.0, target_t[batch])
        loss = nn.functional.smooth_l1_loss(net(torch.from_numpy(frames[a]), torch.from_numpy(frames[b])), goal)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.name}.tmp")
    save_file(net.state_dict(), str(tmp))
    tmp.replace(out_path)
    out_path.with_suffix(".json").write_text(json.dumps({"train_data": str(train_npz), "steps": steps, "seed": seed,
                                                        "still_share": still_share}))
    return net.eval()


def load_motion_estimator(path) -> MotionNet:
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
