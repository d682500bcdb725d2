"""Does the world model obey its controls? (`python diagnose.py control`, evaluation/diagnostics.py)

From each of N starts (windows spread over a token dataset), the world model environment (envs/world_model.py) holds
one control for K steps: each button alone (TURN_LEFT, TURN_RIGHT, MOVE_FORWARD, MOVE_BACKWARD, USE) and NONE (no
button), each from the same start with the same sampler seed. Each pair of consecutive frames gives two measures,
from the frames alone:
- the horizontal shift of the image by phase correlation (`horizontal_shift`, pixels, positive: the content moves
  right, as it does when the view turns left);
- the forward motion: the motion estimator's forward displacement (sample_world/motion_estimator.py, map units,
  negative: backward) when one is given, else the zoom of the image about its centre (`zoom_change`, percent,
  positive: the content grows, as when walking forward).
A start's value per control is the mean over its K steps. A model that obeys (`CHECKS`): turns the image one way
for TURN_LEFT and the other way for TURN_RIGHT; moves it less sideways walking forward than turning; moves forward
for MOVE_FORWARD and backward for MOVE_BACKWARD (at least BACK_RATIO as far as forward goes: a view that barely
moves has not walked back); and keeps it still for NONE and for USE alone (a camera that
stands: less than STILL_RATIO of forward's motion and of the turns' shift; a door may open in front). When the
dataset is a sample world's split, the same starts and controls are played in the real world too (envs/doom.py) as
the reference.
"""
from typing import Dict, List, Optional, Sequence

import numpy as np
from tqdm import tqdm

CONTROL_ACTIONS = ("TURN_LEFT", "TURN_RIGHT", "MOVE_FORWARD", "MOVE_BACKWARD", "USE", "NONE")
NO_BUTTON = "NONE"  # the control that holds no button
BACK_RATIO = 0.1  # backward must move back at least this share of forward's motion (the real world: 0.29-1.1)
STILL_RATIO = 0.25  # "still": under this share of forward's motion and of the turns' shift (a coasting start moves)
ZOOM_LOG_RANGE = 0.4  # the zoom search spans scales exp(-0.4) to exp(0.4) a step (content shrinking or growing ~50 %)
ZOOM_STEPS = 81  # scales tried in that range (0.01 apart in log scale), refined by a parabola
ZOOM_RADIUS = 0.3  # compared over the centre square, +-0.3 of the frame: a shrunk view stays inside the frame
# the checks of a summary's "checks": name -> what passes, for a reader
CHECKS = {
    "turns_opposite": "TURN_LEFT shifts the image right and TURN_RIGHT left (mean shift)",
    "forward_less_sideways": "MOVE_FORWARD shifts the image less sideways than either turn (mean |shift|)",
    "forward_moves_forward": "MOVE_FORWARD moves the view forward (mean forward motion > 0)",
    "backward_moves_back": f"MOVE_BACKWARD moves the view backward (mean forward motion below -{BACK_RATIO:.0%} of "
                           "MOVE_FORWARD's)",
    "none_still": f"NONE moves the view under {STILL_RATIO:.0%} of MOVE_FORWARD's motion and of the turns' shift",
    "use_still": f"USE alone moves the view under {STILL_RATIO:.0%} of MOVE_FORWARD's motion and of the turns' shift",
}


def control_buttons(name: str, button_names: Sequence[str]) -> np.ndarray:
    """A control's held buttons: one button by name, or none for NO_BUTTON."""
    from envs.doom import buttons_from_names

    return buttons_from_names([] if name == NO_BUTTON else [name], button_names)


def _gray(frame_HW3: np.ndarray) -> np.ndarray:
    return frame_HW3.astype(np.float64).mean(axis=-1)


def _gray_windowed(frame_HW3: np.ndarray) -> np.ndarray:
    gray = _gray(frame_HW3)
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
    shift = col + _parabola_offset(left, peak, right, maximum=True)
    return float(shift - W if shift > W / 2 else shift)


def _parabola_offset(left: float, middle: float, right: float, maximum: bool) -> float:
    """Where a parabola through three equally spaced values peaks (or bottoms), relative to the middle one."""
    curvature = left - 2 * middle + right
    if (curvature < 0) if maximum else (curvature > 0):
        return float(0.5 * (left - right) / curvature)
    return 0.0


def _blur(gray_HW: np.ndarray) -> np.ndarray:
    """A small binomial blur, so the zoom search's error varies smoothly with the scale."""
    k = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16
    padded = np.pad(gray_HW, 2, mode="edge")
    rows = sum(k[i] * padded[i: i + gray_HW.shape[0]] for i in range(5))
    return sum(k[i] * rows[:, i: i + gray_HW.shape[1]] for i in range(5))


def _bilinear(image_HW: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    H, W = image_HW.shape
    y, x = np.clip(y, 0, H - 1.001), np.clip(x, 0, W - 1.001)
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - y0, x - x0
    top = image_HW[y0, x0] * (1 - fx) + image_HW[y0, x0 + 1] * fx
    bottom = image_HW[y0 + 1, x0] * (1 - fx) + image_HW[y0 + 1, x0 + 1] * fx
    return top * (1 - fy) + bottom * fy


def zoom_change(before_HW3: np.ndarray, after_HW3: np.ndarray, shift: float = 0.0) -> float:
    """Percent (100 x log scale) the content of `before` grew about the frame's centre in `after` (negative: shrank),
    after moving it `shift` pixels right (a turn's shift, horizontal_shift): the scale whose zoom of `before` best
    matches `after` over the centre square (least squared difference of the mean-removed gray levels), refined by
    a parabola. Walking forward grows the view (near things most), walking backward shrinks it."""
    before, after = _blur(_gray(before_HW3)), _blur(_gray(after_HW3))
    H, W = before.shape
    cy, cx = (H - 1) / 2, (W - 1) / 2
    ry, rx = int(ZOOM_RADIUS * H), int(ZOOM_RADIUS * W)
    y, x = np.mgrid[-ry: ry + 1, -rx: rx + 1].astype(np.float64)
    target = _bilinear(after, cy + y, cx + x)
    target = target - target.mean()
    logs = np.linspace(-ZOOM_LOG_RANGE, ZOOM_LOG_RANGE, ZOOM_STEPS)
    errors = []
    for log_scale in logs:
        scale = np.exp(log_scale)
        guess = _bilinear(before, cy + y / scale, cx + (x - shift) / scale)
        errors.append(np.mean((guess - guess.mean() - target) ** 2))
    errors = np.asarray(errors)
    i = int(np.argmin(errors))
    offset = _parabola_offset(errors[i - 1], errors[i], errors[i + 1], maximum=False) if 0 < i < len(logs) - 1 else 0.0
    return float(100 * (logs[i] + offset * (logs[1] - logs[0])))


def step_motion(frames_N: np.ndarray, estimator=None):
    """(K + 1) consecutive frames -> (shifts (K,) pixels, forward (K,)): the horizontal shift of each step, and its
    forward motion: the estimator's forward map units (MotionNet.motion) when one is given, else zoom_change."""
    shifts = np.array([horizontal_shift(a, b) for a, b in zip(frames_N[:-1], frames_N[1:])])
    if estimator is not None:
        forward = np.asarray(estimator.motion(np.asarray(frames_N)))[:, 0]
    else:
        forward = np.array([zoom_change(a, b, s) for a, b, s in zip(frames_N[:-1], frames_N[1:], shifts)])
    return shifts, forward


def rollout_motion(env, action, steps: int, reset_kwargs: dict, estimator=None) -> tuple:
    """(mean horizontal shift, mean forward motion) per step while `env` holds `action` for `steps` steps from
    reset(**reset_kwargs)."""
    frame, _ = env.reset(**reset_kwargs)
    frames = [frame] + [env.step(action)[0] for _ in range(steps)]
    shifts, forward = step_motion(np.stack(frames), estimator)
    return float(shifts.mean()), float(forward.mean())


def _still(shift, forward, ref_forward, ref_shift):
    """Whether a control kept the view still, against walking forward's motion and the turns' shift (arrays or
    means alike)."""
    return (np.abs(forward) < STILL_RATIO * np.abs(ref_forward)) & (np.abs(shift) < STILL_RATIO * ref_shift)


def summarize(shifts: Dict[str, List[float]], forwards: Dict[str, List[float]]) -> dict:
    """Per-start mean shift and forward motion of each control (CONTROL_ACTIONS) -> their means, the shares of starts
    where each control shows, and the checks over the means (CHECKS: name -> passed), "passed" when all do."""
    s = {a: np.asarray(shifts[a], dtype=np.float64) for a in CONTROL_ACTIONS}
    f = {a: np.asarray(forwards[a], dtype=np.float64) for a in CONTROL_ACTIONS}
    left, right, forward = s["TURN_LEFT"], s["TURN_RIGHT"], s["MOVE_FORWARD"]
    turn_each = np.minimum(np.abs(left), np.abs(right))  # per start
    turn_mean = min(np.mean(np.abs(left)), np.mean(np.abs(right)))
    walk_mean = np.mean(np.abs(f["MOVE_FORWARD"]))

    def still_share(a):
        return float(np.mean(_still(s[a], f[a], f["MOVE_FORWARD"], turn_each)))

    def still_mean(a):
        return bool(_still(np.mean(np.abs(s[a])), np.mean(np.abs(f[a])), walk_mean, turn_mean))

    checks = {
        "turns_opposite": bool(np.mean(left) > 0 > np.mean(right)),
        "forward_less_sideways": bool(np.mean(np.abs(forward)) < turn_mean),
        "forward_moves_forward": bool(np.mean(f["MOVE_FORWARD"]) > 0),
        "backward_moves_back": bool(np.mean(f["MOVE_BACKWARD"]) < -BACK_RATIO * abs(np.mean(f["MOVE_FORWARD"]))),
        "none_still": still_mean(NO_BUTTON),
        "use_still": still_mean("USE"),
    }
    return {
        "mean_shift": {a: float(np.mean(s[a])) for a in CONTROL_ACTIONS},
        "mean_forward": {a: float(np.mean(f[a])) for a in CONTROL_ACTIONS},
        "opposite_turns_share": float(np.mean(np.sign(left) * np.sign(right) < 0)),
        "left_right_share": float(np.mean((left > 0) & (right < 0))),
        "forward_less_sideways_share": float(np.mean(np.abs(forward) < turn_each)),
        "forward_less_sideways_mean": checks["forward_less_sideways"],
        "forward_share": float(np.mean(f["MOVE_FORWARD"] > 0)),
        "backward_share": float(np.mean(f["MOVE_BACKWARD"] < 0)),
        "forward_backward_share": float(np.mean(f["MOVE_FORWARD"] > f["MOVE_BACKWARD"])),
        "none_still_share": still_share(NO_BUTTON),
        "use_still_share": still_share("USE"),
        "checks": checks,
        "passed": all(checks.values()),
    }


def summary_lines(world: str, summary: dict, forward_unit: str) -> List[str]:
    """Readable lines of a summary: the means per control, then each check with what it asks."""
    means = ", ".join(f"{a} {summary['mean_shift'][a]:+.2f} px / {summary['mean_forward'][a]:+.2f}"
                      for a in CONTROL_ACTIONS)
    lines = [f"{world}: per step, shift / forward ({forward_unit}): {means}"]
    for name, what in CHECKS.items():
        lines.append(f"{world}:   {'pass' if summary['checks'][name] else 'FAIL'}  {what}")
    return lines


def control_check(env, starts: Sequence[int], steps: int, seed: int, real_env=None, raw_npz=None,
                  progress: bool = True, estimator=None) -> dict:
    """The check over dataset windows `starts` (module doc), forward motion by `estimator` (a MotionNet) or, when
    None, by the zoom: {"num_starts", "steps", "forward_measure", "model": summary, "real": summary or None,
    "per_start": [{"window", "model": {control: shift}, "real": ..., "model_forward": {control: forward},
    "real_forward": ...}]}."""
    from envs.doom import recorded_start

    actions = {a: control_buttons(a, env.button_names) for a in CONTROL_ACTIONS}
    worlds = {"model": env, "real": real_env}
    shifts = {w: {a: [] for a in CONTROL_ACTIONS} for w, e in worlds.items() if e is not None}
    forwards = {w: {a: [] for a in CONTROL_ACTIONS} for w in shifts}
    per_start = []
    for i, window in enumerate(tqdm(starts, desc="control check", unit="start", disable=not progress)):
        row = {"window": int(window), "model": {}, "real": {} if real_env is not None else None,
               "model_forward": {}, "real_forward": {} if real_env is not None else None}
        resets = {"model": {"seed": seed + i, "options": {"window": int(window)}}}
        if real_env is not None:
            resets["real"] = {"options": recorded_start(raw_npz, env.window_start_frame(int(window)))}
        for name, action in actions.items():
            for world in shifts:
                shift, forward = rollout_motion(worlds[world], action, steps, resets[world], estimator)
                shifts[world][name].append(shift)
                forwards[world][name].append(forward)
                row[world][name], row[f"{world}_forward"][name] = shift, forward
        per_start.append(row)
    return {"num_starts": len(starts), "steps": steps,
            "forward_measure": "motion_estimator" if estimator is not None else "zoom",
            "model": summarize(shifts["model"], forwards["model"]),
            "real": summarize(shifts["real"], forwards["real"]) if real_env is not None else None,
            "per_start": per_start}
