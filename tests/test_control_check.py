"""python diagnose.py control (evaluation/control_check.py): the horizontal shift by phase correlation and the zoom,
their sign conventions in the real world for every control, the checks' pass/fail logic, and the check end to end on
a tiny model beside a tiny real world."""
import json

import numpy as np
import pytest

from evaluation.control_check import (CONTROL_ACTIONS, CHECKS, control_buttons, horizontal_shift, step_motion,
                                      summarize, zoom_change)

pytest.importorskip("vizdoom")


def test_horizontal_shift_finds_a_rolled_image():
    rng = np.random.default_rng(0)
    image = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
    smooth = np.asarray(np.cumsum(np.cumsum(image.astype(float), 0), 1) % 256, dtype=np.uint8)
    for shift in (3, -5, 11):
        assert horizontal_shift(smooth, np.roll(smooth, shift, axis=1)) == pytest.approx(shift, abs=0.3)
    assert horizontal_shift(smooth, np.roll(smooth, 4, axis=0)) == pytest.approx(0, abs=0.3)  # vertical only


def _smooth_image(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = (rng.random((64, 64, 3)) * 255).astype(np.uint8)
    return np.asarray(np.cumsum(np.cumsum(image.astype(float), 0), 1) % 256, dtype=np.uint8)


def _zoomed(image: np.ndarray, scale: float, shift: float = 0.0) -> np.ndarray:
    """`image` grown `scale` times about its centre and moved `shift` pixels right (bilinear, edges repeated)."""
    H, W, _ = image.shape
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    sy, sx = (H - 1) / 2 + (y - (H - 1) / 2) / scale, (W - 1) / 2 + (x - shift - (W - 1) / 2) / scale
    sy, sx = np.clip(sy, 0, H - 1.001), np.clip(sx, 0, W - 1.001)
    y0, x0 = sy.astype(int), sx.astype(int)
    fy, fx = (sy - y0)[..., None], (sx - x0)[..., None]
    f = image.astype(np.float64)
    out = ((f[y0, x0] * (1 - fx) + f[y0, x0 + 1] * fx) * (1 - fy)
           + (f[y0 + 1, x0] * (1 - fx) + f[y0 + 1, x0 + 1] * fx) * fy)
    return out.round().astype(np.uint8)


def test_zoom_change_finds_a_zoomed_image():
    smooth = _smooth_image()
    for scale in (1.2, 0.85, 1.05):
        assert zoom_change(smooth, _zoomed(smooth, scale)) == pytest.approx(100 * np.log(scale), abs=1.5)
    assert zoom_change(smooth, smooth) == pytest.approx(0, abs=0.5)
    turned = _zoomed(smooth, 1.15, shift=6.0)  # a step forward while turning: the shift is taken out first
    assert zoom_change(smooth, turned, shift=6.0) == pytest.approx(100 * np.log(1.15), abs=2.0)


def test_forward_motion_comes_from_the_estimator_when_given():
    class Estimator:
        def motion(self, frames):
            return np.tile([[7.0, 0.0, 0.0]], (len(frames) - 1, 1))

    frames = np.stack([_smooth_image(), _smooth_image(), _smooth_image()])
    shifts, forward = step_motion(frames, Estimator())
    assert shifts.shape == forward.shape == (2,) and (forward == 7.0).all()
    assert np.abs(step_motion(frames)[1]).max() < 0.5  # the zoom: identical frames do not move


def test_real_world_controls_move_the_image_the_documented_way():
    from sample_world import render as sw
    from envs.doom import DoomEnv

    env = DoomEnv(maps=["MAP01"], cfg=sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60))
    try:
        shift, forward = {}, {}
        for name in CONTROL_ACTIONS:
            frame, _ = env.reset(options={"episode_seed": 9, "frame": 60})  # standing in a room, space around
            frames = [frame] + [env.step(control_buttons(name, sw.BUTTON_NAMES))[0] for _ in range(2)]
            shift[name], forward[name] = (v.mean() for v in step_motion(np.stack(frames)))
    finally:
        env.close()
    assert shift["TURN_LEFT"] > 5 and shift["TURN_RIGHT"] < -5  # 13 degrees a step: about 10 pixels
    assert abs(shift["MOVE_FORWARD"]) < min(abs(shift["TURN_LEFT"]), abs(shift["TURN_RIGHT"]))
    assert forward["MOVE_FORWARD"] > 5 and forward["MOVE_BACKWARD"] < -2  # percent of zoom a step
    assert abs(forward["NONE"]) < 1.5 and abs(forward["USE"]) < 1.5 and abs(shift["NONE"]) < 1


def _obeying(n: int = 4) -> tuple:
    """Per-start (shifts, forwards) of a model that obeys every control."""
    shifts = {"TURN_LEFT": [9.0] * n, "TURN_RIGHT": [-9.0] * n, "MOVE_FORWARD": [0.3] * n, "MOVE_BACKWARD": [0.2] * n,
              "USE": [0.1] * n, "NONE": [-0.1] * n}
    forwards = {"TURN_LEFT": [-2.0] * n, "TURN_RIGHT": [-2.0] * n, "MOVE_FORWARD": [20.0] * n,
                "MOVE_BACKWARD": [-8.0] * n, "USE": [1.0] * n, "NONE": [0.5] * n}
    return shifts, forwards


def test_summary_counts_starts_where_the_controls_show():
    shifts, forwards = _obeying(3)
    shifts.update({"TURN_LEFT": [5.0, 4.0, -1.0], "TURN_RIGHT": [-5.0, 3.0, 2.0], "MOVE_FORWARD": [0.5, 0.1, 3.0],
                   "NONE": [-0.1, -0.1, 0.5]})
    forwards.update({"MOVE_BACKWARD": [-8.0, 3.0, -1.0], "NONE": [0.5, 9.0, 0.5]})
    s = summarize(shifts, forwards)
    assert s["left_right_share"] == pytest.approx(1 / 3) and s["opposite_turns_share"] == pytest.approx(2 / 3)
    assert s["forward_less_sideways_share"] == pytest.approx(2 / 3) and s["forward_less_sideways_mean"]
    assert s["backward_share"] == pytest.approx(2 / 3) and s["forward_share"] == 1.0
    # NONE is still at the first start only: at the second it moves 9, not under a quarter of forward's 20; at the
    # third it shifts 0.5 pixels, not under a quarter of that start's smaller turn (1 pixel)
    assert s["none_still_share"] == pytest.approx(1 / 3)
    assert set(s["mean_shift"]) == set(s["mean_forward"]) == set(CONTROL_ACTIONS)


def test_checks_pass_an_obeying_model_and_fail_each_disobedience():
    shifts, forwards = _obeying()
    s = summarize(shifts, forwards)
    assert s["passed"] and set(s["checks"]) == set(CHECKS) and all(s["checks"].values())
    disobedient = {  # check -> a change of one control that breaks it alone
        "turns_opposite": ("shift", "TURN_RIGHT", 9.0),
        "forward_less_sideways": ("shift", "MOVE_FORWARD", 9.5),
        "forward_moves_forward": ("forward", "MOVE_FORWARD", -20.0),
        "backward_moves_back": ("forward", "MOVE_BACKWARD", 8.0),  # backward walks forward: never learned
        "none_still": ("forward", "NONE", 15.0),  # no button keeps walking
        "use_still": ("shift", "USE", 4.0),  # USE turns the view
    }
    for check, (what, control, value) in disobedient.items():
        shifts, forwards = _obeying()
        (shifts if what == "shift" else forwards)[control] = [value] * 4
        s = summarize(shifts, forwards)
        assert not s["passed"] and [k for k, ok in s["checks"].items() if not ok] == [check], check
    shifts, forwards = _obeying()
    forwards["MOVE_BACKWARD"] = [-1.5] * 4  # back, but under a tenth of forward's 20: the view barely moves
    assert [k for k, ok in summarize(shifts, forwards)["checks"].items() if not ok] == ["backward_moves_back"]
    forwards["MOVE_BACKWARD"] = [-2.5] * 4
    assert summarize(shifts, forwards)["passed"]


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
                                                "--steps", "2", "--num_threads", "1",
                                                "--motion_estimator", str(tmp_path / "none.safetensors")])
    assert code == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["num_starts"] == 2 and len(result["per_start"]) == 2
    assert result["real"]["left_right_share"] == 1.0  # the real world obeys, from the model's own starts
    assert result["real"]["checks"]["turns_opposite"] and result["real"]["checks"]["forward_moves_forward"]
    assert set(result["model"]["mean_shift"]) == set(result["model"]["mean_forward"]) == set(CONTROL_ACTIONS)
    assert set(result["per_start"][0]["real_forward"]) == set(CONTROL_ACTIONS)
    assert result["forward_measure"] == "zoom" and result["motion_estimator"] is None  # no estimator file
