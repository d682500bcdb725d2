"""The world model as a Gymnasium environment (envs/world_model.py): the Gymnasium contract, starts, the sliding
context and its cached step against recomputing the window, and clear errors."""
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from data import RawTokenDataset
from genie.inference import next_frame
from genie.reference import next_frame_recomputed
from envs.world_model import WorldEnvError, WorldModelEnv
from genie.decoding import DecodingConfig
from tests.play_fixtures import MAIN_DECODING, T, tiny_dataset, tiny_model, tiny_tokenizer


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    root = tmp_path_factory.mktemp("world")
    tokenizer = tiny_tokenizer(root / "tokenizer")
    return {"tokenizer": tokenizer, "data": tiny_dataset(root / "val", tokenizer),
            "model": tiny_model(root / "model"), "latent_model": tiny_model(root / "latent", latent=3),
            "latent_data": tiny_dataset(root / "latent_val", tokenizer, latent=3)}


@pytest.fixture()
def env(world, one_thread):
    return WorldModelEnv.from_checkpoint(world["model"], world["data"])


def test_buttons_model_passes_gymnasium_check(env):
    assert env.action_space.n == 5 and env.button_names[2] == "TURN_LEFT"
    assert env.observation_space.shape == (64, 64, 3)
    check_env(env, skip_render_check=True)


def test_the_environment_decodes_as_the_checkpoint_says_unless_told(world, one_thread):
    recipe = json.loads((Path(__file__).resolve().parents[1] / "recipes" / "sample_world.json").read_text())
    assert DecodingConfig.from_dict(recipe["decoding"]) == MAIN_DECODING  # the fixtures decode as the main command
    env = WorldModelEnv.from_checkpoint(world["model"], world["data"])
    assert env.model.decoding == MAIN_DECODING and env.model.copy_head.copy_bias == 2.0
    greedy = WorldModelEnv.from_checkpoint(world["model"], world["data"], decoding=DecodingConfig())
    assert greedy.model.decoding == DecodingConfig() and greedy.model.copy_head.copy_bias == 0.0
    frames = []
    for _ in range(2):  # greedy decoding: the same start and actions give the same frames whatever the seed
        greedy.reset(seed=len(frames), options={"window": 1})
        frames.append(greedy.step([0, 0, 1, 0, 0])[0])
    np.testing.assert_array_equal(*frames)


def test_latent_model_passes_gymnasium_check(world, one_thread):
    env = WorldModelEnv.from_checkpoint(world["latent_model"], world["latent_data"])
    assert env.action_space.n == 3
    check_env(env, skip_render_check=True)
    env.reset(seed=1)
    for a in (0, 2, 1):
        frame, *_ = env.step(a)
    with pytest.raises(WorldEnvError, match=r"integer in \[0, 3\)"):
        env.step(3)


def test_window_start_is_the_windows_frames(env, world):
    data = RawTokenDataset(world["data"], window_size=T, stride=15, filter_overlaps=True)
    frame, info = env.reset(options={"window": 1})
    assert info["window"] == 1 and info["context_frames"] == env.prompt_frames == 2
    np.testing.assert_array_equal(info["tokens"], data[1]["tokens"][1].numpy())
    decoded = env.tokenizer.tokens_to_images(data[1]["tokens"][1:2])[0].numpy()
    np.testing.assert_array_equal(frame, decoded)
    # the recorded rows between the given frames (step means, as the model was trained) are the model's, the last
    # one is the player's
    step_mean = data.step_mean_rows("buttons", np.arange(data.valid_start_inds[1], data.valid_start_inds[1] + 1))
    np.testing.assert_allclose(env._actions[0].numpy(), step_mean[0], rtol=1e-6)
    assert 0 < step_mean[0].sum() and not np.isin(step_mean[0], (0, 1)).all()
    assert env._actions[1].isnan().all()
    assert env.window_start_frame(1) == data.valid_start_inds[1] + 15


def test_start_from_frames_and_tokens(env):
    frames = np.random.default_rng(0).integers(0, 256, size=(3, 64, 64, 3), dtype=np.uint8)
    _, info = env.reset(seed=0, options={"frames": frames})
    assert info["window"] is None and info["context_frames"] == 3
    np.testing.assert_array_equal(info["tokens"], env.tokenizer.images_to_tokens(frames[-1:])[0])
    tokens = np.random.default_rng(1).integers(0, 262144, size=(9, 16, 16))
    _, info = env.reset(seed=0, options={"tokens": tokens})
    assert info["context_frames"] == T - 1  # the last T-1 frames
    np.testing.assert_array_equal(info["tokens"], tokens[-1])
    env.step(np.array([1, 0, 0, 0, 0]))


def test_same_seed_same_future_and_actions_matter(env):
    def future(seed, action):
        env.reset(seed=seed, options={"window": 0})
        return [env.step(np.array(action))[4]["tokens"] for _ in range(T + 2)]

    left = future(5, [0, 0, 1, 0, 0])
    np.testing.assert_array_equal(np.stack(left), np.stack(future(5, [0, 0, 1, 0, 0])))
    assert not np.array_equal(np.stack(left), np.stack(future(5, [0, 0, 0, 1, 0])))


@pytest.mark.parametrize("temperature", [0.0, 1.0])
def test_cached_step_equals_recomputing_the_window(env, temperature):
    """Every step, through the growing context and several restarts, gives the frame that recomputing the whole window
    at every MaskGIT step gives from the same context, actions and random state; once the window is full the context
    restarts from its last restart_frames frames (the config's num_prompt_frames), which are the frames before."""
    env.model.set_decoding(env.model.decoding.override(temperature=temperature))
    env.reset(seed=3, options={"window": 2, "prompt_frames": 1})
    P = env.restart_frames
    assert P == env.model.config.num_prompt_frames and 1 < P < T - 1
    rng = np.random.default_rng(0)
    sizes = []
    for _ in range(2 * T + 3):
        action = (rng.random(5) < 0.4).astype(np.int8)
        known = env._tokens.clone()
        tokens, actions, latent = env.step_inputs(action)
        sizes.append(len(tokens))
        np.testing.assert_array_equal(tokens.numpy(), known[-len(tokens):].numpy())  # the latest frames
        np.testing.assert_array_equal(actions[-1].numpy(), action)
        generator = torch.Generator().set_state(env._generator.get_state())
        expected = next_frame_recomputed(env.model, tokens, actions, latent, env.model.decoding.maskgit_steps,
                                         temperature, generator)
        _, _, _, _, info = env.step(action)
        np.testing.assert_array_equal(info["tokens"], expected.numpy())
        assert info["context_frames"] == len(tokens) + 1 <= T
    grow = list(range(P, T))  # P, ..., T-1 context frames, then a restart
    assert sizes == (list(range(1, T)) + grow * T)[:len(sizes)]


def test_cache_is_kept_while_the_context_grows(env):
    """The context's keys/values are computed once: the cache a step returns serves the next one unchanged."""
    env.reset(seed=0, options={"window": 0, "prompt_frames": 1})
    frame_hw, cache = next_frame(env.model, env._tokens, env._actions.clone().nan_to_num(0.0),
                                 torch.zeros(2, dtype=torch.long), None, 2, 0.0)
    assert cache.length == 2
    tokens = torch.cat([env._tokens, frame_hw[None]])
    _, cache = next_frame(env.model, tokens, torch.zeros(2, 5), torch.zeros(3, dtype=torch.long), cache, 2, 0.0)
    assert cache.length == 3
    _, full = next_frame(env.model, torch.cat([tokens, tokens[-1:]]), torch.zeros(T - 1, 5),
                         torch.zeros(T, dtype=torch.long), cache, 2, 0.0)
    assert full is None  # the window is full: the next step restarts the context and recomputes it


def test_bad_input_is_named(env, world, tmp_path):
    with pytest.raises(WorldEnvError, match="call reset"):
        env.step(np.zeros(5))
    env.reset(seed=0)
    for action, match in [(np.array([1, 0, 0]), "5 values of 0 or 1"), (np.array([2, 0, 0, 0, 0]), "0 or 1"),
                          (["TURN_LEFT"], "5 values")]:
        with pytest.raises(WorldEnvError, match=match):
            env.step(action)
    with pytest.raises(WorldEnvError, match=r"window must be an integer in \[0, "):
        env.reset(options={"window": 10**6})
    with pytest.raises(WorldEnvError, match="unknown reset option"):
        env.reset(options={"map": "MAP01"})
    with pytest.raises(WorldEnvError, match="frames must be uint8"):
        env.reset(options={"frames": np.zeros((2, 32, 32, 3), np.uint8)})
    with pytest.raises(WorldEnvError, match="token ids must be in"):
        env.reset(options={"tokens": np.full((2, 16, 16), 262144)})
    no_starts = WorldModelEnv.from_checkpoint(world["model"], None, world["tokenizer"])
    with pytest.raises(WorldEnvError, match="no dataset of starts"):
        no_starts.reset(seed=0)
