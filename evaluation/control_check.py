"""Does the world model obey its controls? (`python diagnose.py control`, evaluation/diagnostics.py)

From each of N starts (windows spread over a token dataset), the world model environment (envs/world_model.py) holds
one button for K steps: TURN_LEFT, TURN_RIGHT, MOVE_FORWARD, each from the same start with the same sampler seed.
Each pair of consecutive frames gives the horizontal shift of the image by phase correlation (`horizontal_shift`,
in pixels, positive: the content moves right, as it does when the view turns left); a start's shift per action is
the mean over its K steps. A model that obeys turns the image one way for TURN_LEFT and the other way for
TURN_RIGHT, and moves it less sideways walking forward. When the dataset is a sample world's split, the same
starts and buttons are played in the real world too (envs/doom.py) as the reference.
"""
from typing import Dict, List, Optional, Sequence

import numpy as np
from tqdm import tqdm

CONTROL_ACTIONS = ("TURN_LEFT", "TURN_RIGHT", "MOVE_FORWARD")


def _gray_windowed(frame_HW3: np.ndarray) -> np.ndarray:
    gray = frame_HW3.astype(np.float64).mean(axis=-1)
    H, W = gray.shape
    return (gray - gray.mean()) * np.outer(np.hanning(H), np.hanning(W))


def horizontal_shift(before_HW3: np.ndarray, after_HW3: np.ndarray) -> float:
    """Pixels the content of `before` moved to the right in `after` (negative: to the left), the column of the
    phase correlation's peak, with a parabola through it and its neighbours for the fraction of a pixel."""
    a, b = np.fft.fft2(_gray_windowed(before_HW3)), np.fft.fft2(_gray_windowed(after_HW3))
    cross = np.conj(a) * b
    corr = np.fft.ifft2(cross / np.maximum(np.abs(cross), 1e-12)).real
    row, col = np.unravel_index(np.argmax(corr), corr.shape)
    W = corr.shape[1]
    left, peak, right = corr[row, (col - 1) % W], corr[row, col], corr[row, (col + 1) % W]
    denominator = left - 2 * peak + right
    fraction = 0.5 * (left - right) / denominator if denominator < 0 else 0.0
    shift = col + fraction
    return float(shift - W if shift > W / 2 else shift)


def rollout_shifts(env, action, steps: int, reset_kwargs: dict) -> float:
    """Mean horizontal shift per step while `env` holds `action` for `steps` steps from reset(**reset_kwargs)."""
    frame, _ = env.reset(**reset_kwargs)
    shifts = []
    for _ in range(steps):
        after, *_ = env.step(action)
        shifts.append(horizontal_shift(frame, after))
        frame = after
    return float(np.mean(shifts))


def summarize(shifts: Dict[str, List[float]]) -> dict:
    """Per-start shifts of each action -> means and the shares of starts where the controls show."""
    left, right, forward = (np.asarray(shifts[a]) for a in CONTROL_ACTIONS)
    return {
        "mean_shift": {a: float(np.mean(shifts[a])) for a in CONTROL_ACTIONS},
        "opposite_turns_share": float(np.mean(np.sign(left) * np.sign(right) < 0)),
        "left_right_share": float(np.mean((left > 0) & (right < 0))),
        "forward_less_sideways_share": float(np.mean(np.abs(forward) < np.minimum(np.abs(left), np.abs(right)))),
        "forward_less_sideways_mean": bool(np.mean(np.abs(forward)) < min(np.mean(np.abs(left)),
                                                                           np.mean(np.abs(right)))),
    }


def control_check(env, starts: Sequence[int], steps: int, seed: int, real_env=None, raw_npz=None,
                  progress: bool = True) -> dict:
    """The check over dataset windows `starts` (module doc): {"num_starts", "steps", "model": summary, "real":
    summary or None, "per_start": [{"window", "model": {action: shift}, "real": ...}]}."""
    from envs.doom import buttons_from_names, recorded_start

    actions = {a: buttons_from_names([a], env.button_names) for a in CONTROL_ACTIONS}
    model = {a: [] for a in CONTROL_ACTIONS}
    real: Optional[dict] = {a: [] for a in CONTROL_ACTIONS} if real_env is not None else None
    per_start = []
    for i, window in enumerate(tqdm(starts, desc="control check", unit="start", disable=not progress)):
        row = {"window": int(window), "model": {}, "real": {} if real is not None else None}
        start = recorded_start(raw_npz, env.window_start_frame(int(window))) if real is not None else None
        for name, action in actions.items():
            shift = rollout_shifts(env, action, steps, {"seed": seed + i, "options": {"window": int(window)}})
            model[name].append(shift)
            row["model"][name] = shift
            if real is not None:
                shift = rollout_shifts(real_env, action, steps, {"options": start})
                real[name].append(shift)
                row["real"][name] = shift
        per_start.append(row)
    return {"num_starts": len(starts), "steps": steps, "model": summarize(model),
            "real": summarize(real) if real is not None else None, "per_start": per_start}
