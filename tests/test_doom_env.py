"""The real sample world as a Gymnasium environment (envs/doom.py): the Gymnasium contract, the action meaning
of one window step, and starts that replay a recorded walk to the frame."""
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

pytest.importorskip("vizdoom")

from sample_world import render as sw  # noqa: E402
from common.errors import InputError  # noqa: E402
from envs.doom import (DoomEnv, EnvInputError, STEP_TICS, buttons_from_names, recorded_start,  # noqa: E402
                           world_config)

FAST = sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60)


@pytest.fixture(scope="module")
def env():
    e = DoomEnv(maps=["MAP01"], cfg=FAST)
    yield e
    e.close()


def test_passes_gymnasium_check(env):
    assert env.action_space.n == 5 and env.observation_space.shape == (64, 64, 3)
    check_env(env, skip_render_check=True)


def test_one_step_is_one_window_step_of_held_buttons(env):
    env.reset(seed=0, options={"frame": 100})
    _, _, _, _, left = env.step(buttons_from_names(["TURN_LEFT"]))
    assert left["motion"][1] == pytest.approx(STEP_TICS * FAST.turn_speed, abs=0.2)  # 13 degrees, counter-clockwise
    _, _, _, _, right = env.step(buttons_from_names(["TURN_RIGHT"]))
    assert right["motion"][1] == pytest.approx(-STEP_TICS * FAST.turn_speed, abs=0.2)
    _, _, _, _, back = env.step(buttons_from_names(["MOVE_BACKWARD"]))
    _, _, _, _, stand = env.step(buttons_from_names([]))
    assert back["motion"][0] < 0 and abs(stand["motion"][1]) < 1e-6


def test_start_replays_the_recorded_walk_to_the_frame(env, tmp_path):
    split = sw.generate_split(("MAP01",), episodes_per_map=2, episode_len=120, seed=5, cfg=FAST, progress=False)
    sw.save_split(tmp_path / "val.npz", split)
    for index in (30, 120 + 77):  # a frame of the first walk, and one of the second
        start = recorded_start(tmp_path / "val.npz", index)
        assert start["map"] == "MAP01" and start["frame"] == index % 120
        frame, info = env.reset(options=start)
        np.testing.assert_array_equal(frame, split["frames"][index])
        np.testing.assert_allclose(info["pose"], split["poses"][index], atol=1e-3)
    with pytest.raises(EnvInputError, match=r"frame 240 out of range \[0, 240\)"):
        recorded_start(tmp_path / "val.npz", 240)


def test_world_config_reads_the_sidecar(tmp_path):
    sw.build_sample_world(tmp_path, train_maps=("MAP01",), val_maps=("MAP01",), train_episodes=1, episode_len=5,
                          workers=1, cfg=sw.WorldConfig(turn_speed=1.75, warmup_min_tics=35, warmup_max_tics=36))
    assert world_config(tmp_path).turn_speed == 1.75
    with pytest.raises(EnvInputError, match="not the raw folder of a sample world"):
        world_config(tmp_path / "nowhere")


def test_bad_input_is_named(env):
    with pytest.raises(InputError, match=r"unknown button\(s\) \['JUMP'\]: the buttons are \['MOVE_FORWARD'"):
        buttons_from_names(["JUMP"])
    with pytest.raises(InputError, match="list of button names"):
        buttons_from_names("TURN_LEFT")
    env.reset(seed=1, options={"frame": 0})
    with pytest.raises(EnvInputError, match="5 values of 0 or 1"):
        env.step(np.array([1, 0]))
    with pytest.raises(EnvInputError, match="unknown reset option"):
        env.reset(options={"window": 3})


# the start below was found with the version-3 walker, whose warm-up walk leads there
V3_WORLD = sw.WorldConfig(**sw.V3_WALKER)


def test_a_walk_out_through_the_exit_keeps_its_last_pose(tmp_path):
    """A policy that walks into a level's exit ends the episode: the steps after it say so, and the pose stays
    where the walk ended (the policies protocol reads it as the return)."""
    from sample_world.policies import check_action, load_policies
    from evaluation.policy_ranking import replay_start

    exit_env = DoomEnv(maps=["MAP28"], cfg=V3_WORLD)
    try:
        policy = load_policies(["wall_hugger"], tmp_path)["wall_hugger"]
        frame = replay_start(exit_env, {"map": "MAP28", "episode_seed": 4206763306, "frame": 72}, 8, 0).prompt_frames[-1]
        policy.reset(0)
        poses, ended = [], []
        for _ in range(18):
            frame, _, terminated, _, info = exit_env.step(check_action(policy.act(frame), "wall_hugger"))
            poses.append(info["pose"])
            ended.append(terminated)
        first_end = ended.index(True)
        assert all(ended[first_end:]) and not any(ended[:first_end])
        assert all(p == poses[first_end - 1] for p in poses[first_end:])
        assert exit_env.pose == poses[first_end - 1]
    finally:
        exit_env.close()


def test_a_teleporter_ends_the_walk_where_it_stood():
    """Backing into a teleporter (MAP28, behind this start) is no walking step: the walk ends before it, with the
    frame and pose of before, as the recorded walks end; without the rule the pose jumps ~4,700 map units."""
    from evaluation.policy_ranking import replay_start

    teleport_env = DoomEnv(maps=["MAP28"], cfg=V3_WORLD)
    try:
        start = replay_start(teleport_env, {"map": "MAP28", "episode_seed": 4206763306, "frame": 72}, 8, 0)
        pose = teleport_env.pose
        frame, _, terminated, _, info = teleport_env.step(buttons_from_names(["MOVE_BACKWARD"]))
        assert terminated and info["teleported"] and info["pose"] == pose == teleport_env.pose
        np.testing.assert_array_equal(frame, start.prompt_frames[-1])
        frame, _, terminated, _, info = teleport_env.step(buttons_from_names(["MOVE_FORWARD"]))
        assert terminated and info["pose"] == pose
        teleport_env.reset(options=start.options)  # a new walk walks again
        _, _, terminated, _, info = teleport_env.step(buttons_from_names(["TURN_LEFT"]))
        assert not terminated and "teleported" not in info
    finally:
        teleport_env.close()
