"""Frames for the latent action model: loading raw-frame .npz files and cutting them into transitions.

A transition ends at target frame f: its past frames are f - P*stride, ..., f - stride (oldest first) and its next
frame is f. It is valid when all of them lie in one segment (episode) of the file.
"""
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from common.errors import InputError
from lam.model import LAM, frames_to_tensor

FRAMES_KEY = "frames"
SEGMENTS_KEY = "segment_ids"
BUTTONS_KEY = "actions_buttons"
BUTTON_NAMES_KEY = "button_names"


def load_frames_npz(path, require_buttons: bool = False) -> dict:
    """Read a raw-frame .npz (the sample world's format) and check it.

    Returns frames (N, H, W, C) uint8, segment_ids (N,) int64, buttons (N, k) float32 or None, button_names (k
    strings) or None. Errors (FileNotFoundError, InputError) name the file and what is wrong.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"frames file not found: {path}")
    try:
        npz = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise InputError(f"{path}: not a readable .npz file ({e})") from None
    with npz:
        missing = [k for k in (FRAMES_KEY, SEGMENTS_KEY) + ((BUTTONS_KEY,) if require_buttons else ()) if k not in npz]
        if missing:
            raise InputError(f"{path}: missing array(s) {missing}; it has {sorted(npz.files)}")
        frames = npz[FRAMES_KEY]
        segment_ids = npz[SEGMENTS_KEY]
        buttons = npz[BUTTONS_KEY] if BUTTONS_KEY in npz else None
        names = [str(n) for n in npz[BUTTON_NAMES_KEY]] if BUTTON_NAMES_KEY in npz else None
    if frames.dtype != np.uint8 or frames.ndim != 4 or frames.shape[-1] not in (1, 3):
        raise InputError(f"{path}: '{FRAMES_KEY}' must be uint8 (N, H, W, 1 or 3), got {frames.dtype} {frames.shape}")
    n = len(frames)
    if segment_ids.shape != (n,) or not np.issubdtype(segment_ids.dtype, np.integer):
        raise InputError(f"{path}: '{SEGMENTS_KEY}' must be integers of shape ({n},), got {segment_ids.dtype} "
                         f"{segment_ids.shape}")
    if buttons is not None:
        if buttons.ndim != 2 or len(buttons) != n:
            raise InputError(f"{path}: '{BUTTONS_KEY}' must have shape ({n}, k), got {buttons.shape}")
        if names is not None and len(names) != buttons.shape[1]:
            raise InputError(f"{path}: {len(names)} button names for {buttons.shape[1]} button columns")
        buttons = buttons.astype(np.float32)
    return {"frames": frames, "segment_ids": segment_ids.astype(np.int64), "buttons": buttons,
            "button_names": names}


def valid_targets(segment_ids: np.ndarray, gap: int) -> np.ndarray:
    """Target frames f (sorted int64) with f - gap >= 0 and frames f - gap .. f all in one segment."""
    if gap <= 0:
        raise ValueError(f"gap must be positive, got {gap}")
    segment_ids = np.asarray(segment_ids)
    # Number of segment changes up to each frame: equal at both ends <=> no change in between (any id order).
    changes = np.concatenate([[0], np.cumsum(segment_ids[1:] != segment_ids[:-1])])
    f = np.arange(gap, len(segment_ids))
    return f[changes[f] == changes[f - gap]]


def gather_transitions(frames_NHWC: torch.Tensor, targets, stride: int, num_past_frames: int,
                       device="cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """uint8 frames (N, H, W, C) + target frames (B,) -> past (B, P, C, H, W) and next (B, C, H, W) in [-1, 1]."""
    targets = torch.as_tensor(np.asarray(targets), dtype=torch.long)
    offsets_P = stride * torch.arange(num_past_frames, 0, -1)  # oldest first
    past_BPHWC = frames_NHWC[targets[:, None] - offsets_P[None, :]]
    next_BHWC = frames_NHWC[targets]
    return frames_to_tensor(past_BPHWC.to(device)), frames_to_tensor(next_BHWC.to(device))


@torch.no_grad()
def infer_codes(model: LAM, frames_NHWC: torch.Tensor, targets: np.ndarray, batch_size: int, device,
                desc: str = "infer latent actions") -> np.ndarray:
    """(M,) int64 latent action of each transition ending at `targets`."""
    cfg = model.config
    codes = []
    for i in tqdm(range(0, len(targets), batch_size), desc=desc, leave=False):
        past, nxt = gather_transitions(frames_NHWC, targets[i: i + batch_size], cfg.stride, cfg.num_past_frames,
                                       device)
        codes.append(model.infer_actions(past, nxt).cpu())
    return torch.cat(codes).numpy() if codes else np.zeros(0, dtype=np.int64)
