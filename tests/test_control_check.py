"""python diagnose.py control (evaluation/control_check.py): the horizontal shift by phase correlation, its
sign convention in the real world, and the check end to end on a tiny model beside a tiny real world."""
import json

import numpy as np
import pytest

from evaluation.control_check import horizontal_shift, summarize

pytest.importorskip("vizdoom")


def test_horizontal_shift_finds_a_rolled_image():
    rng = np.random.default_rng(0)
    image = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
    smooth = np.asarray(np.cumsum(np.cumsum(image.astype(float), 0), 1) % 256, dtype=np.uint8)
    for shift in (3, -5, 11):
        assert horizontal_shift(smooth, np.roll(smooth, shift, axis=1)) == pytest.approx(shift, abs=0.3)
    assert horizontal_shift(smooth, np.roll(smooth, 4, axis=0)) == pytest.approx(0, abs=0.3)  # vertical only


def test_real_world_turns_shift_the_image_the_documented_way():
    from sample_world import render as sw
    from envs.doom import DoomEnv, buttons_from_names

    env = DoomEnv(maps=["MAP01"], cfg=sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60))
    try:
        shifts = {}
        for name in ("TURN_LEFT", "TURN_RIGHT", "MOVE_FORWARD"):
            frame, _ = env.reset(options={"episode_seed": 11, "frame": 60})
            after, *_ = env.step(buttons_from_names([name]))
            shifts[name] = horizontal_shift(frame, after)
    finally:
        env.close()
    assert shifts["TURN_LEFT"] > 5 and shifts["TURN_RIGHT"] < -5  # 13 degrees a step: about 12 pixels
    assert abs(shifts["MOVE_FORWARD"]) < min(abs(shifts["TURN_LEFT"]), abs(shifts["TURN_RIGHT"]))


def test_summary_counts_starts_where_the_controls_show():
    s = summarize({"TURN_LEFT": [5.0, 4.0, -1.0], "TURN_RIGHT": [-5.0, 3.0, 2.0], "MOVE_FORWARD": [0.5, 0.1, 3.0]})
    assert s["left_right_share"] == pytest.approx(1 / 3) and s["opposite_turns_share"] == pytest.approx(2 / 3)
    assert s["forward_less_sideways_share"] == pytest.approx(2 / 3) and s["forward_less_sideways_mean"]


def test_control_runs_on_a_model_beside_the_real_world(tmp_path, capsys):
    from common.cli import run_main
    from sample_world import render as sw
    from diagnose import main
    from sample_world.build import tokenize_split
    from tests.play_fixtures import tiny_model, tiny_tokenizer

    tokenizer = tiny_tokenizer(tmp_path / "tokenizer")
    sw.build_sample_world(tmp_path / "raw", train_maps=("MAP01",), val_maps=("MAP01",), train_episodes=1,
                          episode_len=120, workers=1, cfg=sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60))
    tokenize_split([tmp_path / "raw" / "val.npz"], tmp_path / "val", tokenizer, str(tokenizer), 8, "cpu", False)
    code = run_main("diagnose.py", main, ["control", "--checkpoint_dir", str(tiny_model(tmp_path / "model")),
                                                "--val_data_dir", str(tmp_path / "val"), "--num_starts", "2",
                                                "--steps", "2", "--num_threads", "1"])
    assert code == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["num_starts"] == 2 and len(result["per_start"]) == 2
    assert result["real"]["left_right_share"] == 1.0  # the real world obeys, from the model's own starts
    assert set(result["model"]["mean_shift"]) == {"TURN_LEFT", "TURN_RIGHT", "MOVE_FORWARD"}
