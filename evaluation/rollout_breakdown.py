"""Split a rollout's per-window scores by what the walker does in each window's future
(`python diagnose.py breakdown`, evaluation/diagnostics.py).

    python diagnose.py per_window ... --per_window_out windows.jsonl
    python diagnose.py breakdown windows.jsonl --val_data_dir data/unseen2/val --column 1

Each window of a --per_window_out file is placed by one number: the mean absolute value of one action column over
its generated frames (each row the mean over its window step, as the models with `action_step_mean` see it; column 1
of the sample world's measured_motion is the turn rate, column 0 the forward speed). The windows are cut into `bins`
groups of equal size by that number, and each group's futures are compared with holding the last prompt frame per
horizon: PSNR gain in dB (and LPIPS against holding's, when the file has LPIPS). A mean over all windows can hide a
group of windows where the futures lose to holding; this shows which motion it is. `breakdown` returns
{"stream", "column", "groups": [{"low", "high", "num_windows", "psnr_gain", "psnr_gain_mean", "lpips_rollout",
"lpips_hold"}, ...]}.
"""
import json
from pathlib import Path
from typing import List

import numpy as np

from common.errors import InputError
from data import RawTokenDataset


class BreakdownError(InputError):
    """A per-window file that does not match the dataset, or a stream / column that the dataset lacks."""


def read_per_window(path) -> List[dict]:
    path = Path(path)
    if not path.is_file():
        raise BreakdownError(f"{path}: no such file (write it with python diagnose.py per_window "
                             f"--per_window_out)")
    lines = []
    for number, text in enumerate(path.read_text().splitlines(), start=1):
        try:
            line = json.loads(text)
        except json.JSONDecodeError as e:
            raise BreakdownError(f"{path}, line {number}: not JSON ({e})") from None
        missing = {"window", "first_frame", "rollout_psnr", "hold_psnr"} - set(line)
        if missing:
            raise BreakdownError(f"{path}, line {number}: lacks {sorted(missing)}; is it a --per_window_out "
                                 f"file of python diagnose.py?")
        lines.append(line)
    if not lines:
        raise BreakdownError(f"{path}: no windows")
    return lines


def motion(lines: List[dict], dataset: RawTokenDataset, stream: str, column: int, num_prompt_frames: int,
           where: str) -> np.ndarray:
    """(N,) mean |stream[:, column]| over each window's generated frames (frames num_prompt_frames..); `dataset`
    reads `stream` as step means (its constructor has already checked that the stream exists)."""
    num_columns = dataset.action_dims[stream]
    if not 0 <= column < num_columns:
        raise BreakdownError(f"{where}: stream {stream!r} has {num_columns} columns, not column {column}")
    values = []
    for line in lines:
        window, first_frame = line["window"], line["first_frame"]
        if not 0 <= window < len(dataset) or int(dataset.valid_start_inds[window]) != first_frame:
            raise BreakdownError(f"{where}: window {window} does not start at frame {first_frame} here; pass the "
                                 f"--val_data_dir, --stride and --num_prompt_frames of the run that wrote it")
        rows = dataset.get_window_actions(first_frame)[stream]
        values.append(float(np.abs(rows[num_prompt_frames:, column]).mean()))
    return np.array(values)


def groups(lines: List[dict], values: np.ndarray, bins: int) -> List[dict]:
    """The windows cut into `bins` equal-size groups by `values` (ascending), each with its per-horizon scores."""
    order = np.argsort(values, kind="stable")
    result = []
    for part in np.array_split(order, min(bins, len(order))):
        gain_h = np.mean([np.subtract(lines[i]["rollout_psnr"], lines[i]["hold_psnr"]) for i in part], axis=0)
        group = {"low": float(values[part].min()), "high": float(values[part].max()), "num_windows": len(part),
                 "psnr_gain": gain_h.tolist(), "psnr_gain_mean": float(gain_h.mean()),
                 "lpips_rollout": None, "lpips_hold": None}
        if all("rollout_lpips" in lines[i] for i in part):
            group["lpips_rollout"] = float(np.mean([lines[i]["rollout_lpips"] for i in part]))
            group["lpips_hold"] = float(np.mean([lines[i]["hold_lpips"] for i in part]))
        result.append(group)
    return result


def breakdown(per_window, val_data_dir, stream: str, column: int, bins: int, num_prompt_frames: int,
              stride: int) -> dict:
    """The windows of the --per_window_out file `per_window`, of the dataset `val_data_dir` read as the run that
    wrote it read it (`stride`, `num_prompt_frames`), in `bins` groups by |stream[:, column]| (module doc)."""
    lines = read_per_window(per_window)
    window_size = num_prompt_frames + len(lines[0]["rollout_psnr"])
    dataset = RawTokenDataset(val_data_dir, window_size=window_size, stride=stride, filter_overlaps=True,
                              step_mean_streams=(stream,))
    values = motion(lines, dataset, stream, column, num_prompt_frames, val_data_dir)
    return {"stream": stream, "column": column, "groups": groups(lines, values, bins)}


def describe(result: dict) -> List[str]:
    """One readable line per group of a `breakdown` result."""
    lines = []
    for group in result["groups"]:
        lpips = ("" if group["lpips_rollout"] is None else
                 f"  LPIPS {group['lpips_rollout']:.3f} (hold {group['lpips_hold']:.3f})")
        lines.append(f"|{result['stream']}[{result['column']}]| {group['low']:.3g}-{group['high']:.3g}, "
                     f"{group['num_windows']} windows: {group['psnr_gain_mean']:+.2f} dB over holding, per horizon "
                     f"{' '.join(f'{v:+.2f}' for v in group['psnr_gain'])}{lpips}")
    return lines
