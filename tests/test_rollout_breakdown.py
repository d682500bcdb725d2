"""python diagnose.py breakdown (evaluation/rollout_breakdown.py): the windows of a --per_window_out file grouped
by their future's motion."""
import json

import numpy as np
import pytest

from data import RawTokenDataset, write_token_dataset
from common.cli import run_main
from diagnose import main

T, P, STRIDE = 6, 2, 2


@pytest.fixture
def world(tmp_path):
    """A dataset of one-window clips whose turn rate (measured_motion column 1) is -k in the k-th, and a per-window file whose futures gain k dB at every horizon (LPIPS k / 100, holding's 0.5)."""
    span = (T - 1) * STRIDE + 1
    num_windows = 7
    turn = np.repeat(-np.arange(num_windows, dtype=np.float32), span)
    drive = np.stack([np.ones_like(turn), turn], axis=1)
    video = np.zeros((len(turn), 4, 4), dtype=np.int64)
    segment_ids = np.repeat(np.arange(num_windows), span)  # one clip per window
    data = write_token_dataset(tmp_path / "val", video, segment_ids, actions={"measured_motion": drive},
                               metadata={"vocab_size": 16})
    dataset = RawTokenDataset(data, window_size=T, stride=STRIDE, filter_overlaps=True)
    assert len(dataset) == num_windows
    lines = []
    for window in (3, 0, 6, 1, 5, 2, 4):  # any order: the tool sorts by motion
        first = int(dataset.valid_start_inds[window])
        lines.append({"window": window, "first_frame": first, "rollout_psnr": [20.0 + window] * (T - P),
                      "hold_psnr": [20.0] * (T - P), "rollout_lpips": [window / 100] * (T - P),
                      "hold_lpips": [0.5] * (T - P)})
    per_window = tmp_path / "windows.jsonl"
    per_window.write_text("".join(json.dumps(line) + "\n" for line in lines))
    return data, per_window


def run(capsys, data, per_window, *extra):
    code = run_main("diagnose.py", main, ["breakdown", str(per_window), "--val_data_dir", str(data),
                                                "--num_prompt_frames", str(P), "--stride", str(STRIDE), *extra])
    captured = capsys.readouterr()
    if code:  # one error line, no traceback
        assert "Traceback" not in captured.err and captured.out == ""
        return code, captured.err.strip().splitlines()[-1]
    return code, json.loads(captured.out.strip().splitlines()[-1])


def test_windows_are_grouped_by_the_size_of_their_future_turns(world, capsys):
    code, result = run(capsys, *world, "--bins", "3")
    assert code == 0
    groups = result["groups"]
    assert [g["num_windows"] for g in groups] == [3, 2, 2]
    assert [(g["low"], g["high"]) for g in groups] == [(0, 2), (3, 4), (5, 6)]  # |turn| ascending
    assert [g["psnr_gain_mean"] for g in groups] == pytest.approx([1, 3.5, 5.5])
    assert groups[0]["psnr_gain"] == pytest.approx([1] * (T - P))
    assert [g["lpips_rollout"] for g in groups] == pytest.approx([0.01, 0.035, 0.055])
    assert all(g["lpips_hold"] == pytest.approx(0.5) for g in groups)


def test_forward_speed_column_puts_every_window_in_one_group_of_equal_speed(world, capsys):
    code, result = run(capsys, *world, "--column", "0", "--bins", "1")
    assert code == 0
    (group,) = result["groups"]
    assert (group["low"], group["high"], group["num_windows"]) == (1, 1, 7)
    assert group["psnr_gain_mean"] == pytest.approx(3)


@pytest.mark.parametrize("extra, message", [
    (["--column", "2"], "has 2 columns, not column 2"),
    (["--stream", "buttons"], "no action stream(s) ['buttons.bin']"),
])
def test_mismatches_are_clear_errors(world, capsys, extra, message):
    code, err = run(capsys, *world, *extra)
    assert code == 1 and message in err


def test_scores_of_another_dataset_are_a_clear_error(world, capsys):
    data, per_window = world
    lines = per_window.read_text().splitlines()
    moved = json.loads(lines[0])
    moved["first_frame"] += 1
    per_window.write_text("\n".join([json.dumps(moved)] + lines[1:]) + "\n")
    code, err = run(capsys, data, per_window)
    assert code == 1 and f"window {moved['window']} does not start at frame {moved['first_frame']}" in err


def test_a_file_that_is_not_per_window_scores_is_a_clear_error(world, capsys, tmp_path):
    data, _ = world
    wrong = tmp_path / "summary.jsonl"
    wrong.write_text(json.dumps({"protocol": "rollout", "rollout_psnr": [20.0]}) + "\n")
    code, err = run(capsys, data, wrong)
    assert code == 1 and "lacks ['first_frame', 'hold_psnr', 'window']" in err
    code, err = run(capsys, data, tmp_path / "missing.jsonl")
    assert code == 1 and "no such file" in err
