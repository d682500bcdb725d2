"""How far the camera moved between two frames, from the pixels alone: an inverse-dynamics estimate that never reads
the actions, so a world model's imagined frames and the real ones are measured the same way.

`MotionNet`: two (64, 64, 3) frames one window step (15 tics) apart -> (forward displacement in map units, turn in
degrees, counter-clockwise positive), trained on the sample world's recorded frames and measured motion
(`train_motion_estimator`). `distance_from_start` dead-reckons a walk's frames into how far it ended from where it
began.
"""
import json
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

STRIDE = 15
HZ = 35.0


class MotionNet(nn.Module):
    """(B, 64, 64, 3) frame pairs (before, after) uint8 -> (B, 2) normalized (forward, turn)."""

    def __init__(self):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(6, 32, 4, stride=2, padding=1), nn.ReLU(), nn.Conv2d(32, 64, 4, stride=2, padding=1), nn.ReLU(),
            nn.Conv2d(64, 64, 4, stride=2, padding=1), nn.ReLU(), nn.Flatten(), nn.Linear(64 * 8 * 8, 128),
            nn.ReLU(), nn.Linear(128, 2))
        self.register_buffer("scale", torch.ones(2))  # map units and degrees per normalized unit

    def forward(self, before_BHW3: torch.Tensor, after_BHW3: torch.Tensor) -> torch.Tensor:
        x = torch.cat([before_BHW3, after_BHW3], dim=-1).permute(0, 3, 1, 2).float() / 127.5 - 1.0
        return self.net(x)

    @torch.no_grad()
    def motion(self, frames_NHW3: np.ndarray) -> np.ndarray:
        """(N + 1) consecutive frames -> (N, 2) (forward map units, turn degrees) of each step."""
        f = torch.from_numpy(np.ascontiguousarray(frames_NHW3))
        return (self(f[:-1], f[1:]) * self.scale).numpy()


def step_motion(measured_N2: np.ndarray, segment_ids: np.ndarray):
    """(frame indices t, (forward units, turn degrees) from t to t + 15) for every t with a whole step in its walk,
    from the per-tic measured motion (map units/s along the heading, rad/s)."""
    n = len(measured_N2)
    t = np.arange(n - STRIDE)
    t = t[segment_ids[t] == segment_ids[t + STRIDE]]
    cumulative = np.concatenate([np.zeros((1, 2)), np.cumsum(measured_N2.astype(np.float64) / HZ, axis=0)])
    total = cumulative[t + STRIDE] - cumulative[t]
    return t, np.stack([total[:, 0], np.degrees(total[:, 1])], axis=1).astype(np.float32)


def train_motion_estimator(train_npz, out_path, steps: int = 2000, seed: int = 0, progress: bool = True) -> MotionNet:
    """Fit MotionNet to the recorded walks of train_npz (frames, actions_measured_motion, segment_ids); saved at
    out_path (.safetensors, with a .json of what it was trained on)."""
    from tqdm import tqdm

    with np.load(train_npz) as npz:
        frames, measured, segment_ids = npz["frames"], npz["actions_measured_motion"], npz["segment_ids"]
    index, target = step_motion(measured, segment_ids)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = MotionNet()
    net.scale.copy_(torch.from_numpy(target.std(axis=0)).clamp(min=1e-3))
    target_t = torch.from_numpy(target) / net.scale
    optimizer = torch.optim.Adam(net.parameters(), lr=1e-3)
    for _ in tqdm(range(steps), desc="motion estimator", disable=not progress):
        batch = rng.integers(len(index), size=64)
        t = index[batch]
        loss = nn.functional.smooth_l1_loss(net(torch.from_numpy(frames[t]), torch.from_numpy(frames[t + STRIDE])),
                                            target_t[batch])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_path.with_name(f".{out_path.name}.tmp")
    save_file(net.state_dict(), str(tmp))
    tmp.replace(out_path)
    out_path.with_suffix(".json").write_text(json.dumps({"train_data": str(train_npz), "steps": steps, "seed": seed}))
    return net.eval()


def load_motion_estimator(path) -> MotionNet:
    net = MotionNet()
    net.load_state_dict(load_file(str(path)))
    return net.eval()


def dead_reckon(steps_N2: Sequence) -> np.ndarray:
    """(N, 2) (forward, turn degrees) per step -> (N + 1, 2) positions from (0, 0), heading 0 at the start; each step
    moves along the heading it starts with, then turns."""
    position, heading, path = np.zeros(2), 0.0, [np.zeros(2)]
    for forward, turn in np.asarray(steps_N2, dtype=np.float64).reshape(-1, 2):
        position = position + forward * np.array([np.cos(heading), np.sin(heading)])
        heading += np.radians(turn)
        path.append(position)
    return np.stack(path)


def distance_from_start(steps_N2: Sequence) -> float:
    """How far from the start a walk of these step motions ends, in map units."""
    return float(np.linalg.norm(dead_reckon(steps_N2)[-1]))
