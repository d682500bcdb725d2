"""Tests of the ViZDoom sample-world generator: layout, action meaning, determinism, split disjointness, CLI."""
import dataclasses
import json
import os
import sys
import time

import numpy as np
import pytest

pytest.importorskip("vizdoom")

from sample_world import render as sw  # noqa: E402

# Short warm-up keeps the tests fast; 35 tics is still past the frozen first tics of an episode.
FAST = sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60)
MAPS = ("MAP01", "MAP04")


@pytest.fixture(scope="module")
def split():
    return sw.generate_split(MAPS, episodes_per_map=2, episode_len=300, seed=0, cfg=FAST, progress=False)


def test_layout_shapes_and_dtypes(split):
    n = 2 * 2 * 300
    assert split["frames"].shape == (n, 64, 64, 3) and split["frames"].dtype == np.uint8
    assert split["segment_ids"].shape == (n,) and split["segment_ids"].dtype == np.int32
    assert split["actions_buttons"].shape == (n, len(sw.BUTTON_NAMES))
    assert split["actions_buttons"].dtype == np.float32
    for key in ("actions_driving_command", "actions_measured_motion"):
        assert split[key].shape == (n, 2) and split[key].dtype == np.float32
        assert np.isfinite(split[key]).all()
    assert int(split["hz"]) == sw.HZ == 35
    assert list(split["button_names"]) == list(sw.BUTTON_NAMES)
    assert list(split["maps"]) == ["MAP01", "MAP01", "MAP04", "MAP04"]
    # One id per episode, increasing, each episode exactly episode_len frames.
    assert np.array_equal(split["segment_ids"], np.repeat(np.arange(4, dtype=np.int32), 300))


def test_frames_look_like_a_walk(split):
    frames = split["frames"].astype(np.float32)
    assert 10 < frames.mean() < 200  # neither black nor blown out
    per_frame_std = frames.reshape(len(frames), -1).std(axis=1)
    assert np.median(per_frame_std) > 10  # textured views, not a flat wall colour
    # Consecutive frames of an episode change (the walker moves), episodes differ from each other.
    ep = split["frames"][:300].astype(np.int16)
    assert np.abs(np.diff(ep, axis=0)).mean() > 1
    assert not np.array_equal(split["frames"][0], split["frames"][300])


def test_buttons_are_consistent_choices(split):
    b = split["actions_buttons"]
    assert set(np.unique(b)) <= {0.0, 1.0}
    names = list(sw.BUTTON_NAMES)
    fwd, back = b[:, names.index("MOVE_FORWARD")], b[:, names.index("MOVE_BACKWARD")]
    left, right = b[:, names.index("TURN_LEFT")], b[:, names.index("TURN_RIGHT")]
    assert not np.any((fwd == 1) & (back == 1)) and not np.any((left == 1) & (right == 1))
    assert fwd.mean() > 0.4  # the explorer prefers walking
    assert (left + right).mean() > 0.05  # and turns now and then


def test_driving_command_is_what_the_buttons_command(split):
    """driving_command is the commanded velocity (the 1X meaning): a function of the held buttons alone."""
    b, dc = split["actions_buttons"], split["actions_driving_command"]
    np.testing.assert_allclose(dc, sw.driving_command(b, FAST))
    fwd, back, left, right = b[:, 0] == 1, b[:, 1] == 1, b[:, 2] == 1, b[:, 3] == 1
    np.testing.assert_allclose(dc[fwd & ~back, 0], FAST.top_speed)
    np.testing.assert_allclose(dc[~fwd & ~back, 0], 0.0)
    np.testing.assert_allclose(dc[left & ~right, 1], np.deg2rad(FAST.turn_speed) * sw.HZ, rtol=1e-6)
    np.testing.assert_allclose(dc[right & ~left, 1], -np.deg2rad(FAST.turn_speed) * sw.HZ, rtol=1e-6)
    assert abs(FAST.top_speed - 145.83) < 0.01  # Doom's terminal speed at half its walking thrust


def test_measured_motion_follows_the_command_but_walls_stop_it(split):
    b, dc, mm = split["actions_buttons"], split["actions_driving_command"], split["actions_measured_motion"]
    fwd, left, right = b[:, 0] == 1, b[:, 2] == 1, b[:, 3] == 1
    linear, angular = mm[:, 0], mm[:, 1]
    assert linear[fwd].mean() > 40  # map units/s; top walking speed is about 146
    assert linear[fwd].mean() > linear[~fwd].mean() + 20
    # a sustained walk reaches the commanded top speed
    assert abs(np.percentile(linear[fwd], 90) - FAST.top_speed) < 0.1 * FAST.top_speed
    # Turning has no momentum: every turn tic rotates by exactly turn_speed degrees, as commanded.
    np.testing.assert_allclose(angular[left], dc[left, 1], rtol=0.01)  # ViZDoom rounds to its angle units
    np.testing.assert_allclose(angular[right], dc[right, 1], rtol=0.01)
    np.testing.assert_allclose(angular[~left & ~right], 0.0, atol=1e-3)
    # Forward is commanded at full speed while walls and momentum make the measured speed lower
    assert (linear[fwd] < 0.5 * FAST.top_speed).mean() > 0.05


def test_measured_motion_is_forward_difference_of_poses(split):
    """Row t describes the motion from frame t to frame t+1 (checked inside the first episode)."""
    poses, mm = split["poses"][:300].astype(np.float64), split["actions_measured_motion"][:300]
    dist = np.hypot(*np.diff(poses[:, :2], axis=0).T) * sw.HZ
    turn = (np.diff(poses[:, 2]) + 180) % 360 - 180
    np.testing.assert_allclose(mm[:-1, 1], np.deg2rad(turn) * sw.HZ, atol=1e-3)
    # linear is the displacement projected on the heading: never longer than it, and nearly all of it.
    assert np.all(np.abs(mm[:-1, 0]) <= dist + 1e-2)
    assert np.abs(mm[:-1, 0]).sum() > 0.9 * dist.sum()


def test_measured_motion_convention():
    # Heading 90 degrees (north), moving 2 units north per tic, then turning left across the 360/0 wrap.
    poses = np.array([[0, 0, 90], [0, 2, 90], [0, 4, 90], [0, 4, 359], [0, 4, 1]], dtype=np.float32)
    mm = sw.measured_motion(poses, hz=35)
    assert mm.shape == (4, 2) and mm.dtype == np.float32
    np.testing.assert_allclose(mm[:2], [[70, 0], [70, 0]], atol=1e-3)
    assert mm[2, 1] < 0  # 90 -> 359 is a 91 degree right turn
    np.testing.assert_allclose(mm[3], [0, np.deg2rad(2) * 35], atol=1e-4)  # 359 -> 1 is +2 degrees


def _fake_episode(poses):
    return {"frames": np.zeros((len(poses), 64, 64, 3), np.uint8), "poses": poses}


def test_is_good_episode_rejects_short_and_trapped_walks():
    n = 400
    walk = np.stack([np.arange(n) * 4.0, np.zeros(n), np.zeros(n)], axis=1)  # 4 units per tic to the east
    closet = np.stack([np.full(n, 10.0), np.full(n, 10.0), np.arange(n) % 360.0], axis=1)  # spinning in place
    assert sw.is_good_episode(_fake_episode(walk), n, FAST)
    assert not sw.is_good_episode(_fake_episode(closet), n, FAST)
    assert not sw.is_good_episode(_fake_episode(walk[: n // 4]), n, FAST)  # cut by a teleporter or an exit


def test_same_seed_is_byte_identical_and_seeds_differ():
    kwargs = dict(maps=("MAP09",), episodes_per_map=1, episode_len=80, cfg=FAST, progress=False)
    a = sw.generate_split(seed=3, **kwargs)
    b = sw.generate_split(seed=3, **kwargs)
    c = sw.generate_split(seed=4, **kwargs)
    for key in ("frames", "segment_ids", "actions_buttons", "actions_driving_command", "actions_measured_motion",
                "poses"):
        assert a[key].tobytes() == b[key].tobytes(), key
    assert a["frames"].tobytes() != c["frames"].tobytes()


def test_workers_do_not_change_the_result(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    kwargs = dict(maps=("MAP04",), episodes_per_map=2, episode_len=40, seed=0, cfg=FAST, progress=False,
                  episodes_per_task=1)
    one, two = sw.generate_split(workers=1, **kwargs), sw.generate_split(workers=2, **kwargs)
    for key in ("frames", "segment_ids", "actions_buttons", "actions_driving_command"):
        assert one[key].tobytes() == two[key].tobytes(), key
    # each engine keeps its _vizdoom.ini and _vizdoom/ in a private folder: engines started together in one
    # folder race to create them, and the user's working directory stays clean
    assert os.listdir(tmp_path) == []
    assert os.getcwd() == str(tmp_path)


def _claim(marker: str) -> bool:
    """True for the first caller only (across processes)."""
    try:
        os.close(os.open(marker, os.O_CREAT | os.O_EXCL))
        return True
    except FileExistsError:
        return False


def _fail_once(task):
    """Return `value`; a task with `how` set hangs or kills its worker the first time any worker runs it."""
    marker, value, how = task
    if how and _claim(marker):
        if how == "hang":
            time.sleep(60)
        os._exit(1)
    return value


def _hang(task):
    time.sleep(60)


def _raise(task):
    raise ValueError(f"bad task {task}")


@pytest.mark.parametrize("how", ["hang", "die"])
def test_map_in_order_reruns_the_tasks_of_a_stuck_or_dead_worker(tmp_path, capsys, how):
    marker = str(tmp_path / "claimed")
    tasks = [(marker, i, how if i == 2 else None) for i in range(5)]
    assert list(sw.map_in_order(_fail_once, tasks, workers=2, stall_timeout_s=2)) == list(range(5))
    assert "task 3 of 5 gave no result" in capsys.readouterr().err


def test_map_in_order_gives_up_on_a_second_stall_and_passes_errors_through():
    with pytest.raises(RuntimeError, match="task 1 of 2 gave no result in 1 s, twice"):
        list(sw.map_in_order(_hang, [0, 1], workers=2, stall_timeout_s=1))
    with pytest.raises(ValueError, match="bad task 0"):
        list(sw.map_in_order(_raise, [0, 1], workers=2))


def test_train_and_val_are_disjoint():
    assert not set(sw.HELDOUT_MAPS) & set(sw.TRAIN_MAPS)
    seeds = {split: {sw.episode_seed(0, split, m, e, attempt) for m in sw.TRAIN_MAPS for e in range(50)
                     for attempt in range(FAST.max_attempts)} for split in ("train", "val")}
    assert len(seeds["train"]) == len(seeds["val"]) == 50 * len(sw.TRAIN_MAPS) * FAST.max_attempts
    assert not seeds["train"] & seeds["val"]
    kwargs = dict(maps=("MAP01",), episodes_per_map=1, episode_len=40, seed=0, cfg=FAST, progress=False)
    train = sw.generate_split(split="train", **kwargs)
    val = sw.generate_split(split="val", **kwargs)
    assert train["episode_seeds"][0] != val["episode_seeds"][0]
    assert not np.array_equal(train["frames"], val["frames"])


def test_episode_maps_come_from_freedoom1_and_unknown_maps_name_their_wad():
    """ExMy names render Freedoom: Phase 1's maps (36 more than MAPxx's 32); a bad name of either kind is refused with
    the WAD that lacks it, before ViZDoom starts (it would hang on a missing map)."""
    assert [sw.wad_name(m) for m in ("E1M1", "E4M9", "MAP01", "MAP32")] == ["freedoom1.wad"] * 2 + ["freedoom2.wad"] * 2
    assert not sw.is_episode_map("EXM1") and not sw.is_episode_map("E1M10")
    assert len(sw.wad_maps(sw._wad_path("E1M1"))) == 36 and sw.wad_maps(sw._wad_path("MAP01"))[-1] == "MAP32"
    with pytest.raises(ValueError, match=r"\['E5M1'\]: .*freedoom1.wad has E1M1..E4M9; \['MAP40'\]: .*freedoom2.wad"):
        sw.check_maps(["E1M1", "E5M1", "MAP01", "MAP40"])
    with pytest.raises(ValueError, match="none given"):
        sw.check_maps([])
    walk = sw.generate_split(("E1M1", "MAP01"), episodes_per_map=1, episode_len=40, seed=0, cfg=FAST, progress=False)
    assert list(walk["maps"]) == ["E1M1", "MAP01"] and walk["frames"].shape == (80, 64, 64, 3)
    e1m1 = walk["frames"][:40].astype(np.int16)
    assert np.abs(np.diff(e1m1, axis=0)).mean() > 1  # a walk through a lit map, not a frozen or black screen


def test_train_episode_len_shortens_training_walks_and_keeps_validation(tmp_path):
    """Shorter training walks (more maps at the same frames) leave the validation split byte for byte as it was; the
    sidecar of a world built without the option does not change (existing worlds are not rebuilt)."""
    kwargs = dict(train_maps=("MAP01",), val_maps=("MAP18",), train_episodes=1, episode_len=30, workers=1, cfg=FAST)
    assert sw.build_sample_world(tmp_path / "long", **kwargs)
    assert sw.build_sample_world(tmp_path / "short", train_episode_len=20, **kwargs)
    long_params = json.loads((tmp_path / "long" / sw.SIDECAR_NAME).read_text())
    short_params = json.loads((tmp_path / "short" / sw.SIDECAR_NAME).read_text())
    assert "episode_len" not in long_params["train"] and short_params["train"]["episode_len"] == 20
    # what was asked for is the same but the training split (the button statistics differ with the walks)
    assert ({k: v for k, v in short_params.items() if k not in ("train", sw.STATS_KEY)}
            == {k: v for k, v in long_params.items() if k not in ("train", sw.STATS_KEY)})
    assert short_params[sw.STATS_KEY]["val"] == long_params[sw.STATS_KEY]["val"]
    with np.load(tmp_path / "long" / "val.npz") as a, np.load(tmp_path / "short" / "val.npz") as b:
        for key in ("frames", "segment_ids", "actions_buttons", "actions_driving_command"):
            assert a[key].tobytes() == b[key].tobytes(), key
    with np.load(tmp_path / "long" / "train.npz") as a, np.load(tmp_path / "short" / "train.npz") as b:
        assert a["frames"].shape[0] == 30 and b["frames"].shape[0] == 20
        assert b["frames"].tobytes() == a["frames"][:20].tobytes()  # the same walk, stopped sooner
    assert not sw.build_sample_world(tmp_path / "short", train_episode_len=20, **kwargs)  # matching sidecar: skipped
    # a length equal to episode_len is the long world, sidecar and all
    assert sw.build_sample_world(tmp_path / "short", train_episode_len=30, **kwargs)
    assert json.loads((tmp_path / "short" / sw.SIDECAR_NAME).read_text()) == long_params


def test_cli_writes_npz_and_second_run_is_a_noop(tmp_path, monkeypatch, capsys):
    out = tmp_path / "raw"
    argv = ["sample_world", "--output_dir", str(out), "--seed", "1", "--train_maps", "MAP01", "--val_maps", "MAP18",
            "--train_episodes", "1", "--val_episodes", "1", "--episode_len", "30", "--workers", "1"]
    monkeypatch.setattr(sys, "argv", argv)
    sw.main()
    files = {p.name for p in out.iterdir()}
    assert files == {"train.npz", "val.npz", sw.SIDECAR_NAME}  # no temp files left behind
    with np.load(out / "train.npz") as f:
        assert f["frames"].shape == (30, 64, 64, 3)
        assert f["actions_buttons"].shape == (30, 5) and f["actions_driving_command"].shape == (30, 2)
        assert f["actions_measured_motion"].shape == (30, 2)
        assert int(f["hz"]) == 35 and list(f["maps"]) == ["MAP01"]
    with np.load(out / "val.npz") as f:
        assert list(f["maps"]) == ["MAP18"]
    sidecar = json.loads((out / sw.SIDECAR_NAME).read_text())
    assert sidecar["seed"] == 1
    with np.load(out / "train.npz") as f:  # the statistics of what was walked, beside the parameters
        assert sidecar[sw.STATS_KEY]["train"] == sw.button_stats(f["actions_buttons"], f["segment_ids"])
    assert sidecar[sw.STATS_KEY]["val"]["per_tic"]["rows"] == 30
    mtimes = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    capsys.readouterr()

    sw.main()
    assert "skipping" in capsys.readouterr().out
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == mtimes

    monkeypatch.setattr(sys, "argv", argv + ["--overwrite"])
    sw.main()
    assert (out / "train.npz").stat().st_mtime_ns != mtimes["train.npz"]


def test_other_walker_turns_by_its_turn_speed():
    fast = sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60, turn_speed=1.75)  # the walker of earlier versions
    data = sw.generate_split(("MAP01",), episodes_per_map=1, episode_len=200, seed=0, cfg=fast, progress=False)
    left, right = data["actions_buttons"][:, 2] == 1, data["actions_buttons"][:, 3] == 1
    assert left.sum() + right.sum() > 0
    turn_rate = np.deg2rad(1.75) * sw.HZ  # twice the default's
    angular = data["actions_measured_motion"][:, 1]
    np.testing.assert_allclose(angular[left], turn_rate, rtol=0.02)
    np.testing.assert_allclose(angular[right], -turn_rate, rtol=0.02)
    with pytest.raises(ValueError, match="turn_speed > 0"):
        sw.WorldConfig(turn_speed=0.0)
    with pytest.raises(ValueError, match="walk_speed > 0"):
        sw.WorldConfig(walk_speed=-1.0)


def test_build_sample_passes_turn_speed_and_workers(tmp_path, monkeypatch, capsys):
    from sample_world import build as build_sample

    seen = {}

    def fake_build(out_dir, cfg=None, workers=None, **kwargs):
        seen["cfg"], seen["workers"] = cfg, workers
        raise SystemExit(0)  # stop before tokenizing

    monkeypatch.setattr(build_sample, "build_sample_world", fake_build)
    with pytest.raises(SystemExit):
        build_sample.main(["--output_dir", str(tmp_path), "--turn_speed", "0.5"])
    assert seen["cfg"].turn_speed == 0.5
    with pytest.raises(SystemExit):
        build_sample.main(["--output_dir", str(tmp_path)])
    assert seen["cfg"] == sw.WorldConfig()  # the default world is unchanged
    with pytest.raises(SystemExit, match="2"):
        build_sample.main(["--output_dir", str(tmp_path), "--turn_speed", "0"])
    assert "--turn_speed must be > 0" in capsys.readouterr().err
    assert seen["workers"] == 2  # the default
    with pytest.raises(SystemExit):
        build_sample.main(["--output_dir", str(tmp_path), "--workers", "8"])
    assert seen["workers"] == 8
    with pytest.raises(SystemExit, match="2"):
        build_sample.main(["--output_dir", str(tmp_path), "--workers", "0"])
    assert "--workers must be >= 1" in capsys.readouterr().err


def test_button_stats_count_tics_and_window_rows():
    """Shares per tic and over every 15th tic of each walk (the rows a window gives a model): a one-tic USE is a
    tic's share but no window row's."""
    n = sw.STEP_TICS
    walk = np.zeros((4 * n, 5), np.float32)
    walk[:n, 0] = 1  # forward for a step
    walk[n: 2 * n, [1, 2]] = 1  # backward and left
    walk[2 * n: 3 * n, 3] = 1  # turn right in place
    walk[3 * n + 1, 4] = 1  # a one-tic USE, then nothing
    other = np.zeros((n + 1, 5), np.float32)
    other[:, 4] = 1  # a second walk pressing USE: rows 0 and 15 of it
    stats = sw.button_stats(np.concatenate([walk, other]), np.repeat([0, 1], [len(walk), len(other)]))
    tic, row = stats["per_tic"], stats["per_window_row"]
    assert tic["rows"] == 5 * n + 1 and row["rows"] == 4 + 2
    assert tic["forward"] == pytest.approx(n / (5 * n + 1), abs=1e-4) and row["forward"] == pytest.approx(1 / 6, abs=1e-4)
    assert row["backward"] == row["turn_in_place"] == pytest.approx(1 / 6, abs=1e-4)
    assert row["held"]["TURN_LEFT"] == row["held"]["TURN_RIGHT"] == pytest.approx(1 / 6, abs=1e-4)
    assert row["no_button"] == pytest.approx(1 / 6, abs=1e-4)  # the one-tic USE is not seen ...
    assert tic["use"] == pytest.approx((n + 2) / (5 * n + 1), abs=1e-4) and row["use"] == pytest.approx(2 / 6, abs=1e-4)
    assert tic["no_button"] == pytest.approx((n - 1) / (5 * n + 1), abs=1e-4)  # ... but counted per tic
    assert sw.button_shares(np.zeros((0, 5)))["rows"] == 0


def test_walker_holds_every_behaviour_for_window_steps():
    """One walk's window rows show walking backward, no button and USE (the version-2 walker's show none of them),
    and each of those is held in runs of at least a step."""
    data = sw.generate_split(("MAP01",), episodes_per_map=1, episode_len=1500, seed=0, cfg=FAST, progress=False)
    b = data["actions_buttons"]
    rows = sw.button_stats(b, data["segment_ids"])["per_window_row"]
    assert rows["backward"] >= 0.05 and rows["no_button"] >= 0.03 and rows["use"] >= 0.02
    assert rows["forward"] >= 0.2 and rows["turn_in_place"] >= 0.1
    assert ((b[:, 1] == 1) & (b[:, 2] + b[:, 3] == 1)).any()  # backward with a turn held
    for column in (b[:, 4], (b.sum(axis=1) == 0).astype(np.float32)):  # USE; no button
        edges = np.flatnonzero(np.diff(np.r_[0, column, 0]))
        runs = edges[1::2] - edges[::2]
        assert np.median(runs) >= sw.STEP_TICS - 1, runs
    # USE alone is pressed standing: the view has stopped (a quarter of walking speed at most; it coasted ~40
    # units on when the walker pressed it as it arrived)
    press = np.flatnonzero((b[1:, 4] == 1) & (b[:-1, 4] == 0)) + 1
    alone = press[(b[press, 0] == 0) & (b[press, 1] == 0)]
    speed = np.hypot(*np.diff(data["poses"][:, :2].astype(np.float64), axis=0).T)  # map units per tic
    assert len(alone) and (speed[alone - 1] < 0.25 * FAST.top_speed / sw.HZ).all(), speed[alone - 1]
    assert sw.is_good_episode({"frames": data["frames"], "poses": data["poses"]}, 1500, FAST)


def test_older_worlds_keep_their_walkers():
    """A sidecar of generator version 2 names none of the walker's new settings: they take V2_WALKER's values, the
    walker that recorded those worlds (version 3's take V3_WALKER's) (the real world replays their walks), which never stands still, walks backward
    only now and then and presses USE for single tics."""
    config = {k: v for k, v in dataclasses.asdict(FAST).items() if k not in sw.V2_WALKER}
    config["clear_depth"] = 28  # what version 2 recorded
    v2 = sw.sidecar_world_config({"generator_version": 2, "config": config})
    assert all(getattr(v2, k) == v for k, v in sw.V2_WALKER.items())
    v3_config = {k: v for k, v in dataclasses.asdict(FAST).items() if k not in sw.V3_WALKER}
    v3 = sw.sidecar_world_config({"generator_version": 3, "config": v3_config})
    assert v3.use_settle_tics == 0 and v3 == dataclasses.replace(FAST, use_settle_tics=0)  # presses USE arriving
    assert sw.sidecar_world_config({"generator_version": 4, "config": dataclasses.asdict(FAST)}) == FAST
    data = sw.generate_split(("MAP01",), episodes_per_map=1, episode_len=600, seed=0, cfg=v2, progress=False)
    b = data["actions_buttons"]
    assert not (b.sum(axis=1) == 0).any() and not ((b[:, 1] == 1) & (b[:, 2] + b[:, 3] > 0)).any()
    assert not ((b[1:, 4] == 1) & (b[:-1, 4] == 1)).any()  # no USE held two tics in a row
