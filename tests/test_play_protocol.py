"""The play protocol (evaluation/play_protocol.py, `evaluate.py --protocol play`): scores against the real frames
over long play, its distances and its command line."""
import json

import numpy as np
import pytest
import torch

from common.images import kid, sharpness
from evaluation.play_protocol import horizon_bins, play_starts
from tests.cli_runner import REPO, run_as_main
from tests.test_evaluate import lpips_weights_available


def test_kid_is_near_zero_for_one_distribution_and_grows_with_a_shift():
    rng = np.random.default_rng(0)
    a, b = (torch.from_numpy(rng.normal(size=(300, 16))) for _ in range(2))
    same = kid(a, b)
    shifted = kid(a, b + 0.5)
    assert abs(same) < 0.05 * shifted
    assert kid(a, b + 1.0) > shifted > 0
    assert kid(b + 0.5, a) == pytest.approx(shifted)  # symmetric
    with pytest.raises(ValueError, match="at least 2 rows"):
        kid(a[:1], b)


def test_sharpness_drops_when_an_image_is_blurred():
    rng = np.random.default_rng(0)
    images = torch.from_numpy(rng.integers(0, 256, size=(2, 32, 32, 3), dtype=np.uint8))
    blurred = torch.nn.functional.avg_pool2d(images.permute(0, 3, 1, 2).float(), 3, stride=1, padding=1)
    blurred = blurred.round().clamp(0, 255).to(torch.uint8).permute(0, 2, 3, 1)
    sharp, soft = sharpness(images), sharpness(blurred)
    assert (soft < 0.5 * sharp).all()
    assert sharpness(torch.full((1, 16, 16, 3), 90, dtype=torch.uint8)).item() == 0.0


def test_horizon_bins_stop_at_the_steps_played():
    assert horizon_bins(64) == [(1, 8), (9, 16), (17, 32), (33, 64)]
    assert horizon_bins(20) == [(1, 8), (9, 16), (17, 20)]
    assert horizon_bins(3) == [(1, 3)]


class _Windows:
    def __init__(self, starts, segment_ids):
        self.valid_start_inds, self.segment_ids = np.asarray(starts), np.asarray(segment_ids)


def test_play_starts_spread_over_each_walk():
    # two walks: frames 0-99 and 100-199; windows may start at 0..39 and 100..139
    dataset = _Windows(list(range(40)) + list(range(100, 140)), [0] * 100 + [1] * 100)
    chosen = play_starts(dataset, 3)
    firsts = [int(dataset.valid_start_inds[i]) for i in chosen]
    assert firsts == [0, 20, 39, 100, 120, 139]
    assert [int(dataset.valid_start_inds[i]) for i in play_starts(dataset, 1)] == [0, 100]


pytest.importorskip("vizdoom")


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from tests.play_fixtures import tiny_play_world
    return tiny_play_world(tmp_path_factory.mktemp("play_protocol"))


def _evaluate(world, *extra, figures=None):
    argv = ["--protocol", "play", "--val_data_dir", world["data"], "--checkpoint_dir", world["model"],
            "--device", "cpu", "--num_threads", "1", "--play_steps", "4", "--starts_per_episode", "2", *extra]
    if figures is not None:
        argv += ["--figures_dir", figures]
    return run_as_main({"play": (REPO / "evaluate.py", argv)})["play"]


def test_play_protocol_scores_every_step_against_the_real_frames(world, tmp_path):
    if not lpips_weights_available():
        pytest.skip("no LPIPS weights on this machine (python -m magvit2.lpips_weights makes them)")
    proc = _evaluate(world, figures=tmp_path / "figures")
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["protocol"] == "play" and result["steps"] == 4 and result["prompt_frames"] == 2
    assert result["decoding"]["copy_bias"] == 2.0  # the checkpoint's own decoding
    assert [row["bin"] for row in result["per_bin"]] == ["1-4"]
    for world_name in ("model", "tokenizer", "hold"):
        assert len(result["per_step"][world_name]["psnr"]) == 4
        assert all(np.isfinite(v) for v in result["per_bin"][0][world_name].values())

    # holding: the last prompt frame against the real frame one step on, recorded 15 tics apart
    from data import RawTokenDataset
    dataset = RawTokenDataset(world["data"], window_size=6, stride=15)
    with np.load(world["root"] / "raw" / "val.npz") as npz:
        frames = torch.from_numpy(npz["frames"])
    chosen = play_starts(dataset, 2)
    assert result["num_starts"] == len(chosen) >= 2
    firsts = [int(dataset.valid_start_inds[i]) for i in chosen]
    mse = [((frames[f + 15].double() - frames[f + 30].double()) ** 2).mean().item() for f in firsts]
    expected = np.mean([10 * np.log10(255.0 ** 2 / m) for m in mse])
    assert result["per_step"]["hold"]["psnr"][0] == pytest.approx(expected, rel=1e-4)

    # the tokenizer column decodes the dataset's tokens with the tokenizer its metadata names (not the shipped one)
    from magvit2 import VQModel
    tokenizer = VQModel.from_checkpoint(world["tokenizer"]).eval()
    decoded = [tokenizer.tokens_to_images(dataset[i]["tokens"][2:3].long())[0].double() for i in chosen]
    mse = [((d - frames[f + 30].double()) ** 2).mean().item() for d, f in zip(decoded, firsts)]
    expected = np.mean([10 * np.log10(255.0 ** 2 / m) for m in mse])
    assert result["per_step"]["tokenizer"]["psnr"][0] == pytest.approx(expected, rel=1e-3)

    assert (tmp_path / "figures" / "play_curves.png").stat().st_size > 1000
    from PIL import Image
    with Image.open(tmp_path / "figures" / "play_drive.gif") as gif:
        assert gif.n_frames == 4 and gif.size == (3 * 3 * 68, 3 * 68)  # model | tokenizer | real, 3x


def test_play_protocol_names_what_is_missing(world, tmp_path):
    import shutil
    alone = tmp_path / "copy" / "val"
    shutil.copytree(world["data"], alone)  # a token dataset without its raw frames beside it
    proc = _evaluate({**world, "data": alone})
    assert proc.returncode not in (0, "crash") and "Traceback" not in proc.stderr
    assert "raw/val.npz" in proc.stderr and "real frames" in proc.stderr
    long = _evaluate(world, "--play_steps", "400")
    assert long.returncode not in (0, "crash") and "--play_steps" in long.stderr and "Traceback" not in long.stderr
    bad = _evaluate(world, "--save_outputs_dir", str(tmp_path / "x"))
    assert bad.returncode == 2 and "does not apply to --protocol play" in bad.stderr


def test_step_row_replays_a_recorded_row_as_step_plays_its_buttons(world):
    from envs.world_model import WorldEnvError, WorldModelEnv
    env = WorldModelEnv.from_checkpoint(world["model"], world["data"])
    buttons = np.array([1, 0, 1, 0, 0], dtype=np.int8)
    frames = []
    for replay in (False, True):
        env.reset(seed=3, options={"window": 0})
        frames.append([(env.step_row(buttons.astype(np.float32)) if replay else env.step(buttons))[0]
                       for _ in range(5)])  # past T = 4: the context slides
    np.testing.assert_array_equal(np.stack(frames[0]), np.stack(frames[1]))
    env.reset(seed=3, options={"window": 0})
    env.step_row(np.array([0.4, 0, 0.6, 0, 0], dtype=np.float32))  # a step mean: a share of the tics
    with pytest.raises(WorldEnvError, match="5 finite values"):
        env.step_row(np.array([1.0, np.nan, 0, 0, 0]))
    with pytest.raises(WorldEnvError, match="5 finite values"):
        env.step_row(np.zeros(3))


def test_rollout_protocol_also_scores_against_the_real_frames_where_a_sample_world_has_them(world, tmp_path):
    import shutil
    argv = ["--protocol", "rollout", "--checkpoint_dir", world["model"], "--window_size", "4",
            "--num_prompt_frames", "2", "--device", "cpu", "--num_threads", "1", "--skip_lpips"]
    alone = tmp_path / "copy" / "val"
    shutil.copytree(world["data"], alone)
    procs = run_as_main({"sample": (REPO / "evaluate.py", argv + ["--val_data_dir", world["data"]]),
                         "tokens_only": (REPO / "evaluate.py", argv + ["--val_data_dir", alone])})
    with_real, tokens_only = (json.loads(procs[k].stdout.strip().splitlines()[-1]) for k in ("sample", "tokens_only"))
    for name in ("rollout", "tokenizer", "hold"):
        assert len(with_real[f"{name}_real_psnr"]) == 2 and f"{name}_real_psnr" not in tokens_only
    assert with_real["rollout_psnr"] == tokens_only["rollout_psnr"]  # the challenge's scores do not change

    from data import RawTokenDataset
    dataset = RawTokenDataset(world["data"], window_size=4, stride=15, filter_overlaps=True)
    with np.load(world["root"] / "raw" / "val.npz") as npz:
        frames = npz["frames"].astype(np.float64)
    firsts = [int(f) for f in dataset.valid_start_inds]
    mse = [((frames[f + 15] - frames[f + 30]) ** 2).mean() for f in firsts]  # the last prompt frame, held
    assert with_real["hold_real_psnr"][0] == pytest.approx(np.mean([10 * np.log10(255.0 ** 2 / m) for m in mse]),
                                                           rel=1e-4)
