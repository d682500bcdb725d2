"""The README's main job end to end on a tiny budget: sample world -> tokens -> GENIE -> generate -> GIF -> metrics."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from PIL import Image

from common.train_state import list_checkpoints, load_training_checkpoint
from data import RawTokenDataset
from tests.test_evaluate import lpips_weights_available
from magvit2 import VQConfig, VQModel

REPO = Path(__file__).resolve().parents[1]

pytest.importorskip("vizdoom")


def tiny_tokenizer(path: Path) -> Path:
    """A small random 64x64 tokenizer saved at path: fast to run, real enough for the pipeline's plumbing."""
    VQModel(VQConfig(base_channels=32, ch_mult=[1, 2, 2], num_res_blocks=1, resolution=64)).save_pretrained(path)
    return path


def saved_training_state(output_dir: Path) -> dict:
    """The run's one training checkpoint: the optimizer's groups and the trainer's arguments (what train.py got)."""
    [(_, state_dir)] = list_checkpoints(output_dir)
    return load_training_checkpoint(state_dir)


def test_main_job_pipeline_tiny(tmp_path):
    tokenizer = tiny_tokenizer(tmp_path / "tokenizer")
    sample = tmp_path / "sample"
    build = [sys.executable, "-m", "sample_world.build", "--output_dir", str(sample), "--train_maps", "MAP01",
             "--val_maps", "MAP18", "--train_episodes", "1", "--episode_len", "240", "--tokenizer_ckpt", str(tokenizer)]
    subprocess.run(build, cwd=REPO, check=True, timeout=300)
    train = RawTokenDataset(sample / "train", window_size=16, stride=15)
    assert len(train) > 0 and train.metadata["hz"] == 35
    assert set(train.action_names) == {"buttons", "driving_command", "measured_motion"}

    # A second build is a no-op that keeps the datasets.
    stamp = (sample / "train" / "video.bin").stat().st_mtime
    subprocess.run(build, cwd=REPO, check=True, timeout=300)
    assert (sample / "train" / "video.bin").stat().st_mtime == stamp

    config = tmp_path / "genie.json"
    config.write_text(json.dumps({"num_layers": 1, "num_heads": 2, "d_model": 32, "T": 16, "S": 256,
                                  "image_vocab_size": 262144, "num_prompt_frames": 8, "copy_radius": 1,
                                  "copy_match_input": True, "action_names": ["buttons"],
                                  "action_dim": 5, "action_step_mean": True}))  # as the main command's config
    out = tmp_path / "model"
    env = dict(os.environ, SAMPLE_DIR=str(sample), OUT=str(out), GENIE_CONFIG=str(config),
               EVAL_ARGS="--max_examples 1", LPIPS_EVAL_ARGS="--skip_lpips --max_examples 1", NUM_EXAMPLES="1",
               ROLLOUT_EVAL_ARGS="--skip_lpips --max_examples 1 --num_prompt_frames 8",
               UNSEEN_DIR=str(sample),  # stands in for a set of unseen maps: its val split is another map
               PLAY_ARGS="--play_steps 4 --starts_per_episode 1")
    play = lpips_weights_available()  # the play protocol scores LPIPS and its features
    if not play:
        env["SKIP_PLAY"] = "1"
    subprocess.run(["bash", str(REPO / "run_sample.sh"), "--max_train_steps", "2", "--per_device_train_batch_size", "1",
                    "--eval_every_n_steps", "0", "--num_warmup_steps", "0"], cwd=REPO, env=env, check=True, timeout=600)
    assert (out / "final_checkpt" / "model.safetensors").exists()
    saved = json.loads((out / "final_checkpt" / "config.json").read_text())
    assert saved["action_step_mean"] and len(saved["action_mean"]) == 5  # statistics filled in from the data
    generated = json.loads((out / "generated" / "metadata.json").read_text())
    assert generated["actions_from_data"] and generated["copy_bias"] == 2.0
    assert generated["greedy_tokens"] == "best_neighbour"
    gifs, pngs = list(out.glob("*.gif")), list(out.glob("*.png"))
    assert gifs and pngs
    assert Image.open(gifs[0]).n_frames > 1
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["num_examples"] == 1 and 0 <= metrics["acc"] <= 1 and metrics["pred_lpips"] is None
    assert json.loads((out / "metrics_lpips.json").read_text())["num_examples"] == 1
    baselines = json.loads((out / "baselines.json").read_text())
    assert 0 <= baselines["copy_acc"] <= 1
    rollout = json.loads((out / "metrics_rollout.json").read_text())
    assert (rollout["protocol"], rollout["num_prompt_frames"], rollout["num_examples"]) == ("rollout", 8, 1)
    assert len(rollout["rollout_psnr"]) == len(rollout["hold_ssim"]) == 16 - 8
    assert rollout["rollout_far_psnr"] == rollout["rollout_psnr"][-1] and rollout["rollout_lpips"] is None
    # greedy, the pointer's decoding bias, copies from the single most weighted neighbour
    assert (rollout["temperature"], rollout["copy_bias"], rollout["greedy_tokens"]) == (0.0, 2.0, "best_neighbour")
    sampled = json.loads((out / "metrics_rollout_sampled.json").read_text())
    assert (sampled["temperature"], sampled["copy_bias"], sampled["num_examples"]) == (1.0, 2.0, 1)
    assert rollout["stall_ratio"] is None and generated["stall_ratio"] is None  # off unless asked for
    assert json.loads((out / "metrics_rollout_sampled_unseen.json").read_text())["temperature"] == 1.0
    unseen = json.loads((out / "metrics_unseen.json").read_text())
    assert unseen["num_examples"] == 1 and unseen["copy_acc"] == metrics["copy_acc"]  # same val split here
    assert json.loads((out / "metrics_rollout_unseen.json").read_text())["protocol"] == "rollout"
    if play:
        for name in ("metrics_play.json", "metrics_play_unseen.json"):
            result = json.loads((out / name).read_text())
            assert (result["protocol"], result["steps"], result["num_starts"]) == ("play", 4, 1)
        assert (out / "play_curves.png").exists() and (out / "play_unseen" / "play_drive.gif").exists()
    state = saved_training_state(out)
    decays = {g["weight_decay"] for g in state["optimizer"]["param_groups"]}
    assert decays == {0.0, 0.4}  # the main command's decay on matrices and embeddings, none on biases and norms
    assert state["trainer"]["args"]["lr_scheduler_type"] == "linear"
