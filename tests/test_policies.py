"""Policies (sample_world/policies.py), the motion estimator's dead reckoning (sample_world/motion_estimator.py) and the policy
protocol (evaluation/policy_ranking.py, ./evaluate.py --protocol policies) on hand-made cases."""
import json

import numpy as np
import pytest
import torch

from common.errors import InputError
from sample_world.motion_estimator import (MotionNet, dead_reckon, distance_from_start, load_motion_estimator, pose_motion,
                                          step_pairs)
from sample_world.policies import (MACRO_NAMES, MACROS, UNMATCHED, PolicyError, RandomButtons, Shuttle, check_action,
                                   load_policies, load_policy, macro_ids, macro_targets)


def test_scripted_policies():
    shuttle = Shuttle()
    shuttle.reset(0)
    assert [shuttle.act(None) for _ in range(6)] == [["MOVE_FORWARD"]] * 2 + [["MOVE_BACKWARD"]] * 2 + \
        [["MOVE_FORWARD"]] * 2
    a, b = RandomButtons(), RandomButtons()
    a.reset(3), b.reset(3)
    assert [a.act(None) for _ in range(10)] == [b.act(None) for _ in range(10)]


def _banded_frame(left, centre, right):
    """A (64, 64, 3) frame whose middle band has the given brightness in its left, centre and right thirds."""
    frame = np.full((64, 64, 3), 50, dtype=np.uint8)
    frame[21:42, :21], frame[21:42, 21:43], frame[21:42, 43:] = left, centre, right
    return frame


def test_scripted_and_pixel_driven_policies():
    for name, expected in (("backward", ["MOVE_BACKWARD"]), ("stand", [])):
        policy = load_policy(name)
        policy.reset(0)
        assert policy.act(None) == expected
    a, b = load_policy("dither"), load_policy("dither")
    a.reset(5), b.reset(5)
    steps = [a.act(None) for _ in range(40)]
    assert steps == [b.act(None) for _ in range(40)]
    assert {tuple(x) for x in steps} == {("MOVE_FORWARD",), ("MOVE_BACKWARD",)}
    seeker, hugger = load_policy("dark_seeker"), load_policy("wall_hugger")
    # a bright wall ahead: the seeker turns toward the darker side, the hugger turns left (its wall on the right)
    assert seeker.act(_banded_frame(20, 90, 40)) == ["TURN_LEFT"]
    assert seeker.act(_banded_frame(40, 90, 20)) == ["TURN_RIGHT"]
    assert hugger.act(_banded_frame(40, 90, 60)) == ["TURN_LEFT"]
    # open (dark) ahead: the seeker bears toward the darker side, or walks straight when the sides match
    assert seeker.act(_banded_frame(60, 30, 40)) == ["MOVE_FORWARD", "TURN_RIGHT"]
    assert seeker.act(_banded_frame(50, 40, 50)) == ["MOVE_FORWARD"]
    # the right side opens up: the hugger bears right; a wall close on the right: it walks on
    assert hugger.act(_banded_frame(50, 50, 30)) == ["MOVE_FORWARD", "TURN_RIGHT"]
    assert hugger.act(_banded_frame(40, 50, 70)) == ["MOVE_FORWARD"]


def test_policy_files_load_and_bad_ones_are_named(tmp_path):
    (tmp_path / "mine.py").write_text("class Left:\n    def reset(self, seed): pass\n"
                                      "    def act(self, frame): return ['TURN_LEFT']\n"
                                      "class NoAct:\n    def reset(self, seed): pass\n")
    (tmp_path / "broken.py").write_text("def oops(:\n")
    policy = load_policy(f"{tmp_path / 'mine.py'}:Left")
    assert policy.act(np.zeros((64, 64, 3), np.uint8)) == ["TURN_LEFT"]
    for spec, match in [(f"{tmp_path / 'mine.py'}:NoAct", "has no act"),
                        (f"{tmp_path / 'broken.py'}:X", "does not load: SyntaxError"),
                        (f"{tmp_path / 'mine.py'}:Missing", "does not load: AttributeError"),
                        (f"{tmp_path / 'nowhere.py'}:X", "not found"), ("fly", "unknown policy 'fly'")]:
        with pytest.raises(PolicyError, match=match):
            load_policy(spec, tmp_path)
    with pytest.raises(PolicyError, match="names must differ"):
        load_policies(["spin", "spin"], tmp_path)
    with pytest.raises(PolicyError, match=r"unknown button\(s\) \['JUMP'\]"):
        check_action(["JUMP"], "mine")
    with pytest.raises(PolicyError, match="list of button names"):
        check_action("TURN_LEFT", "mine")


def test_macro_targets_take_the_action_held_most_of_the_step():
    forward, left = np.array([1, 0, 0, 0, 0]), np.array([0, 0, 1, 0, 0])
    buttons = np.stack([forward] * 10 + [left] * 20 + [forward] * 5).astype(np.float32)
    index, target = macro_targets(buttons, np.zeros(35, dtype=np.int64))
    assert list(index) == list(range(21))
    assert MACROS[target[0]] == ("MOVE_FORWARD",) and MACROS[target[5]] == ("TURN_LEFT",)  # 10 of 15 tics left
    _, split = macro_targets(buttons, np.repeat([0, 1], [20, 15]))  # no step crosses two walks
    assert len(split) == 6 + 1


def test_every_button_combination_of_the_walker_has_its_own_macro():
    from sample_world.render import _ACTIONS

    held = {tuple(v) for v in _ACTIONS.values()} | {(0, 0, 0, 0, 1), (1, 0, 0, 0, 1)}  # + USE alone, USE pushing
    rows = np.array(sorted(held), dtype=np.float32)
    assert len(rows) == 11
    ids = macro_ids(rows)
    assert UNMATCHED not in ids and len(set(ids)) == len(rows)
    for row, k in zip(rows, ids):  # each row is labelled with the macro holding exactly its buttons
        np.testing.assert_array_equal(check_action(list(MACROS[k]), "macro"), row)
    named = dict(zip(MACRO_NAMES, MACROS))
    assert macro_ids(np.array([[0, 1, 1, 0, 0], [0, 1, 0, 1, 0], [0, 0, 0, 0, 1], [1, 0, 0, 0, 1], [0] * 5])).tolist() \
        == [MACRO_NAMES.index(n) for n in ("backward_left", "backward_right", "use", "use_forward", "none")]
    assert named["use"] == ("USE",) and named["none"] == ()
    # no macro holds forward and backward, both turns, or a half-held button: those rows are not relabelled
    assert macro_ids(np.array([[1, 1, 0, 0, 0], [0, 0, 1, 1, 0], [0.5, 0, 0, 0, 0]])).tolist() == [UNMATCHED] * 3
    with pytest.raises(PolicyError, match=r"must be \(N, 5\)"):
        macro_ids(np.zeros((3, 4)))


def test_macro_targets_skip_steps_held_mostly_outside_the_macros():
    back_left, odd = np.array([0, 1, 1, 0, 0]), np.array([1, 1, 0, 0, 0])  # odd: forward and backward at once
    buttons = np.stack([back_left] * 15 + [odd] * 15).astype(np.float32)
    index, target = macro_targets(buttons, np.zeros(30, dtype=np.int64))
    # steps from frames 0..7 hold back_left for 8+ of 15 tics; from 8 on the odd rows outnumber it
    assert list(index) == list(range(8)) and {MACROS[t] for t in target} == {("MOVE_BACKWARD", "TURN_LEFT")}


def tiny_walks(path, seed: int):
    """A (40-tic) npz of recorded walks, random frames, every tic backward + right."""
    rng = np.random.default_rng(seed)
    np.savez(path, frames=rng.integers(0, 256, size=(40, 64, 64, 3), dtype=np.uint8),
             actions_buttons=np.tile(np.array([0, 1, 0, 1, 0], np.float32), (40, 1)),
             segment_ids=np.zeros(40, np.int64), poses=rng.normal(size=(40, 3)).astype(np.float32))
    return path


def test_cached_policies_of_other_data_or_macros_are_retrained(tmp_path, monkeypatch, caplog, one_thread):
    from evaluation.policy_ranking import PolicyEvalError, PolicyRankingConfig, ensure_trained
    from sample_world import motion_estimator, policies

    monkeypatch.setattr(policies, "BC_BUDGETS", {"bc_small": 1, "bc_medium": 2, "bc_large": 3})
    trained = []
    train_bc, train_estimator = policies.train_bc_policies, motion_estimator.train_motion_estimator
    monkeypatch.setattr(policies, "train_bc_policies", lambda *a, **k: (trained.append("bc"), train_bc(*a, **k)))
    monkeypatch.setattr(motion_estimator, "train_motion_estimator", lambda *a, **k: (
        trained.append("estimator"), train_estimator(*a, **{**k, "steps": 1, "progress": False})))
    data, policy_dir = tiny_walks(tmp_path / "train.npz", 0), tmp_path / "policies"
    cfg = PolicyRankingConfig(checkpoint_dir="", policies=["bc_large"], policy_dir=str(policy_dir),
                              policy_train_data=str(data))
    record = policy_dir / "bc_policies.json"

    def retrains(what: list, because: str) -> None:
        caplog.clear()
        with caplog.at_level("INFO"):
            ensure_trained(cfg)
        assert trained == what and because in caplog.text, caplog.text
        trained.clear()
        ensure_trained(cfg)  # now recorded as this data's: reused
        assert not trained
        policy = load_policy("bc_large", policy_dir)
        policy.reset(0)
        assert tuple(policy.act(np.zeros((64, 64, 3), np.uint8))) in MACROS

    retrains(["bc", "estimator"], "bc_small.safetensors is not there")
    assert json.loads(record.read_text())["macro_names"] == list(MACRO_NAMES)
    # cloned over the 8 macro actions of before: refused when loaded directly, retrained by the protocol
    record.write_text(json.dumps({**json.loads(record.read_text()), "macros": [[]] * 8}))
    with pytest.raises(PolicyError, match="cloned over 8 other macro actions than this version's 11"):
        load_policy("bc_large", policy_dir)
    retrains(["bc"], "cloned over 8 other macro actions")
    record.write_text(json.dumps({k: v for k, v in json.loads(record.read_text()).items() if k != "source"}))
    retrains(["bc"], "does not record the training data's fingerprint")
    tiny_walks(data, 1)  # another world at the same path
    retrains(["bc", "estimator"], "the training data is now")
    estimator_record = policy_dir / "motion_estimator.json"
    estimator_record.write_text(json.dumps({**json.loads(estimator_record.read_text()), "version": 1}))
    with pytest.raises(InputError, match="motion estimator of version 1, this version reads pairs with version 2"):
        load_motion_estimator(policy_dir / "motion_estimator.safetensors")  # its weights load, but mean another thing
    retrains(["estimator"], "motion estimator of version 1")
    (policy_dir / "motion_estimator.json").write_text("{}")  # an estimator of no recorded data, and the data gone
    data.unlink()
    with pytest.raises(PolicyEvalError, match="train.npz not found.*needed because .*motion_estimator.json does not "
                                              "record"):
        ensure_trained(cfg)


def test_weights_of_another_output_size_are_a_clear_error(tmp_path):
    from safetensors.torch import save_file

    from sample_world import policies

    net = policies.BCNet()
    net.net[-1] = torch.nn.Linear(128, 8)  # the 8 macro actions of before
    save_file(net.state_dict(), str(tmp_path / "bc_large.safetensors"))
    with pytest.raises(PolicyError, match="8 macro outputs, this version has 11"):
        policies.BehaviourCloned(tmp_path / "bc_large.safetensors")
    (tmp_path / "bc_small.safetensors").write_bytes(b"not safetensors")
    with pytest.raises(PolicyError, match="does not load as a cloned policy"):
        policies.BehaviourCloned(tmp_path / "bc_small.safetensors")


def test_pose_motion_step_pairs_and_dead_reckoning_by_hand():
    # heading 90 (north): 30 units north is 30 forward; 10 units west is 10 to the left; then a turn across 360/0
    a = np.array([[0, 0, 90], [0, 0, 90], [0, 0, 350]], np.float32)
    b = np.array([[0, 30, 90], [-10, 0, 90], [0, 0, 20]], np.float32)
    np.testing.assert_allclose(pose_motion(a, b), [[30, 0, 0], [0, 10, 0], [0, 0, 30]], atol=1e-4)
    poses = np.zeros((40, 3), np.float32)
    poses[:, 0] = np.arange(40) * 2.0  # 2 units a tic to the east, heading 0
    first, second, motion = step_pairs(poses, np.repeat([0, 1], [30, 10]))
    assert len(first) == 2 * 15 and set(second - first) == {15, -15}  # each pair both ways, none across walks
    np.testing.assert_allclose(motion[first < second][:, 0], 30.0)
    np.testing.assert_allclose(motion[first > second][:, 0], -30.0)  # played backwards: a backward step
    np.testing.assert_allclose(dead_reckon([[10, 0, 90], [10, 0, 0]])[-1], [10, 10], atol=1e-9)
    np.testing.assert_allclose(dead_reckon([[0, 5, 0]])[-1], [0, 5], atol=1e-9)  # sliding to the left
    assert distance_from_start([[10, 90], [10, 0]]) == pytest.approx(np.sqrt(200))  # (forward, turn) rows
    assert distance_from_start([[10, 0], [-10, 0]]) == pytest.approx(0.0)  # shuttling gets nowhere


def test_motion_net_reads_frames_only_and_a_pair_backwards_as_the_opposite_motion():
    net = MotionNet().eval()
    frames = np.random.default_rng(0).integers(0, 256, size=(4, 64, 64, 3), dtype=np.uint8)
    motion = net.motion(frames)
    assert motion.shape == (3, 3) and np.abs(motion).min() > 0
    np.testing.assert_allclose(net.motion(frames[::-1])[::-1], -motion, rtol=1e-5, atol=1e-6)
    assert not net.motion(np.stack([frames[0], frames[0], frames[0]])).any()  # standing still reads as exactly still


def test_mirrored_pairs_turn_the_other_way():
    from sample_world.motion_estimator import mirrored

    rng = np.random.default_rng(0)
    before, after = (torch.from_numpy(rng.integers(0, 256, size=(2, 64, 64, 3), dtype=np.uint8)) for _ in range(2))
    goal = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    b, a, g = mirrored(before, after, goal, torch.tensor([True, False]))
    assert torch.equal(b[0], before[0].flip(1)) and torch.equal(a[0], after[0].flip(1))  # left and right swapped
    assert torch.equal(b[1], before[1]) and torch.equal(a[1], after[1])
    assert g.tolist() == [[1.0, -2.0, -3.0], [4.0, 5.0, 6.0]]


def test_walks_too_short_for_a_step_are_a_clear_error(tmp_path):
    from sample_world.motion_estimator import train_motion_estimator

    np.savez(tmp_path / "train.npz", frames=np.zeros((10, 64, 64, 3), np.uint8), poses=np.zeros((10, 3), np.float32),
             segment_ids=np.zeros(10, np.int64))
    with pytest.raises(InputError, match="no walk is longer than one step"):
        train_motion_estimator(tmp_path / "train.npz", tmp_path / "estimator.safetensors", steps=1, progress=False)


def test_recoloured_pairs_share_one_colour_change():
    from sample_world.motion_estimator import recoloured

    rng = np.random.default_rng(0)
    grey = np.repeat(rng.integers(60, 200, size=(8, 64, 64, 1), dtype=np.uint8), 3, axis=-1)
    before = torch.from_numpy(grey)
    after = torch.from_numpy(np.roll(grey, 5, axis=2))  # the same picture, moved
    new_before, new_after = recoloured(before, after, np.random.default_rng(1))
    assert new_before.dtype == torch.uint8 and new_before.shape == before.shape
    assert not torch.equal(new_before, before)
    assert torch.equal(torch.roll(new_before, 5, dims=2), new_after)  # one change for both frames: the motion kept
    spread = [new_before[i].float().mean((0, 1)) for i in range(8)]
    assert max(float((s.max() - s.min())) for s in spread) > 5  # grey made coloured: channels scaled apart


# ------------------------------------------------------------------ the protocol, with the real world
vizdoom = pytest.importorskip("vizdoom")


@pytest.fixture(scope="module")
def worlds():
    from sample_world import render as sw
    from envs.doom import DoomEnv

    cfg = sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60)
    envs = [DoomEnv(maps=["MAP01"], cfg=cfg) for _ in range(2)]
    yield envs
    for env in envs:
        env.close()


class IgnoresActions:
    """A 'world model' whose frames do not depend on the buttons: the recorded walk goes on whatever is pressed."""

    def __init__(self, env):
        self.env = env

    def begin(self, start):
        from evaluation.policy_ranking import replay_start

        replay_start(self.env, start.options, len(start.prompt_frames), start.seed)
        return self.env.frame

    def step(self, buttons):
        self.env.follow_explorer(15)
        return self.env.frame


def suite():
    from sample_world.policies import AlwaysForward, Spin

    return {"spin": Spin(), "forward": AlwaysForward(), "shuttle": Shuttle(), "random": RandomButtons()}


def test_the_real_world_as_the_model_reproduces_the_real_frames_ranking(worlds):
    from evaluation.policy_ranking import RealWorld, evaluate_policies, make_starts

    real, twin = worlds
    torch.manual_seed(0)
    estimator = MotionNet().eval()
    starts = make_starts(real, ["MAP01"], 2, 3, seed=1, latest_frame=300)
    result = evaluate_policies(suite(), real, RealWorld(twin), estimator, starts, steps=4, progress=False)
    for row in result["policies"]:
        assert row["model_return"] == pytest.approx(row["real_frames_return"], abs=1e-6)
    assert result["spearman"] == pytest.approx(result["real_frames_spearman"])
    by_name = {r["name"]: r for r in result["policies"]}
    assert by_name["spin"]["real_return"] < by_name["forward"]["real_return"]  # turning in place: coasting only
    assert by_name["forward"]["blind_return"] == pytest.approx(4 * 145.83 * 15 / 35, rel=1e-3)  # walls ignored


def test_a_model_that_ignores_actions_ranks_no_better_than_chance(worlds):
    from evaluation.policy_ranking import evaluate_policies, make_starts

    real, twin = worlds
    starts = make_starts(real, ["MAP01"], 2, 3, seed=2, latest_frame=300)
    result = evaluate_policies(suite(), real, IgnoresActions(twin), MotionNet().eval(), starts, steps=4,
                               progress=False)
    model_returns = {r["model_return"] for r in result["policies"]}
    assert len(model_returns) == 1  # every policy gets the same imagined walk
    assert result["spearman"] == 0.0 and result["pairwise_accuracy"] == 0.5
    # and its uncertainty says so: no resample of the starts ranks, every ordering ties it, every real gap violated
    assert result["spearman_ci"] == (0.0, 0.0) and result["spearman_p"] == 1.0 and result["pearson"] == 0.0
    truth = [r["real_return"] for r in result["policies"]]
    assert result["mmrv"] == pytest.approx(np.mean(truth) - min(truth))  # each policy's gap to the worst
    assert result["num_policies"] == 4 and result["num_starts"] == 2


def test_evaluate_policies_protocol_end_to_end(tmp_path, capsys):
    from common.cli import run_main
    from sample_world import render as sw
    from evaluate import main
    from sample_world.motion_estimator import train_motion_estimator
    from sample_world.policies import stamp_source
    from tests.play_fixtures import tiny_model, tiny_tokenizer

    cfg = sw.WorldConfig(warmup_min_tics=35, warmup_max_tics=60)
    sw.build_sample_world(tmp_path / "raw", train_maps=("MAP01",), val_maps=("MAP01",), train_episodes=1,
                          episode_len=60, workers=1, cfg=cfg)
    train_motion_estimator(tmp_path / "raw" / "train.npz", tmp_path / "policies" / "motion_estimator.safetensors",
                           steps=2, progress=False)
    stamp_source(tmp_path / "policies" / "motion_estimator.json", tmp_path / "raw" / "train.npz")  # else retrained
    (tmp_path / "mine.py").write_text("class Jump:\n    def reset(self, seed): pass\n"
                                      "    def act(self, frame): return ['JUMP']\n")
    args = ["--protocol", "policies", "--checkpoint_dir", str(tiny_model(tmp_path / "model")),
            "--tokenizer_ckpt", str(tiny_tokenizer(tmp_path / "tokenizer")), "--maps", "MAP01", "--starts", "2",
            "--steps", "2", "--policy_dir", str(tmp_path / "policies"), "--policy_train_data",
            str(tmp_path / "raw" / "train.npz"), "--num_threads", "1"]
    assert run_main("evaluate.py", main, [*args, "--policies", "spin", "forward", "shuttle"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [p["name"] for p in result["policies"]] == ["spin", "forward", "shuttle"]
    for key in ("spearman", "kendall", "pairwise_accuracy", "regret_at_1", "blind_spearman", "real_frames_spearman",
                "pearson", "mmrv", "mmrv_share", "spearman_p"):
        assert key in result
    low, high = result["spearman_ci"]
    assert -1 <= low <= high <= 1 and result["num_policies"] == 3 and result["num_starts"] == 2
    from evaluation.policy_ranking import ranking_lines
    assert "permutation p" in ranking_lines(result)[-1]  # the readable lines carry the uncertainty
    assert all(f"{k}_return_std" in p for p in result["policies"] for k in ("real", "model"))
    assert run_main("evaluate.py", main, [*args, "--policies", f"{tmp_path / 'mine.py'}:Jump"]) == 1
    assert "unknown button(s) ['JUMP']" in capsys.readouterr().err
