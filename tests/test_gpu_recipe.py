"""run_gpu.sh end to end on a tiny budget: it refuses a machine without a GPU, and with ALLOW_CPU builds its world,
trains its recipe and scores it as run_sample.sh does (its own file, so that it runs beside the main job's test)."""
import json
import os
import shutil
import subprocess

import pytest

from data import RawTokenDataset
from tests.test_pipeline import REPO, saved_training_state, tiny_tokenizer

pytest.importorskip("vizdoom")


def test_gpu_recipe_refuses_a_cpu_box_and_runs_tiny_when_allowed(tmp_path):
    """run_gpu.sh stops without CUDA before building anything; with ALLOW_CPU it builds, trains and evaluates; with
    SKIP_BUILD it trains on a copied world, and refuses a copy that is cut short or missing."""
    env = dict(os.environ, GPU_DIR=str(tmp_path / "world"), OUT=str(tmp_path / "model"))
    env.pop("ALLOW_CPU", None)
    refused = subprocess.run(["bash", str(REPO / "run_gpu.sh")], cwd=REPO, env=env, capture_output=True, text=True,
                             timeout=120)
    assert refused.returncode == 1 and "no CUDA GPU" in refused.stderr
    assert not (tmp_path / "world").exists()  # stopped before building anything

    tokenizer = tiny_tokenizer(tmp_path / "tokenizer")
    config = tmp_path / "genie.json"
    config.write_text(json.dumps({"num_layers": 1, "num_heads": 2, "d_model": 32, "T": 16, "S": 256,
                                  "image_vocab_size": 262144, "num_prompt_frames": 8, "copy_radius": 1}))
    env.update(ALLOW_CPU="1", EPISODES="1", GENIE_CONFIG=str(config), GENERATE_ARGS="", NUM_EXAMPLES="1",
               TRAIN_MAPS="MAP01", BUILD_ARGS=f"--val_maps MAP18 --episode_len 240 --tokenizer_ckpt {tokenizer}",
               LPIPS_EVAL_ARGS="--skip_lpips --max_examples 1", SKIP_SAMPLED="1",
               ROLLOUT_EVAL_ARGS="--skip_lpips --max_examples 1 --num_prompt_frames 8",
               UNSEEN_DIRS=f"{tmp_path / 'none'} {tmp_path / 'world'}", STALL_RATIO="0.4", SKIP_BASELINES="1", WEIGHT_DECAY="0.1",
               SKIP_PLAY="1")  # the play protocol: tests/test_pipeline.py
    env["STEPS"] = "40"  # the warm-up follows it: STEPS/20 unless WARMUP says otherwise
    subprocess.run(["bash", str(REPO / "run_gpu.sh"), "--per_device_train_batch_size", "1",
                    "--eval_every_n_steps", "0"], cwd=REPO, env=env, check=True, timeout=600)
    built = json.loads((tmp_path / "world" / "raw" / "sample_world.json").read_text())
    assert built["train"] == {"maps": ["MAP01"], "episodes_per_map": 1}  # TRAIN_MAPS and EPISODES reach the builder
    saved = json.loads((tmp_path / "model" / "final_checkpt" / "config.json").read_text())
    assert (saved["d_model"], saved["copy_radius"]) == (32, 1)
    metrics = json.loads((tmp_path / "model" / "metrics.json").read_text())
    windows = len(RawTokenDataset(tmp_path / "world" / "val", window_size=16, stride=15, filter_overlaps=True))
    assert metrics["num_examples"] == windows  # the recipe evaluates every validation window
    rollout = json.loads((tmp_path / "model" / "metrics_rollout.json").read_text())
    assert rollout["protocol"] == "rollout" and rollout["stall_ratio"] == 0.4  # STALL_RATIO reaches both
    assert json.loads((tmp_path / "model" / "generated" / "metadata.json").read_text())["stall_ratio"] == 0.4
    assert not (tmp_path / "model" / "metrics_rollout_sampled.json").exists()
    assert not (tmp_path / "model" / "baselines.json").exists()  # SKIP_BASELINES=1
    # UNSEEN_DIRS: a folder with a val split is scored under its own name, one without is skipped
    unseen = json.loads((tmp_path / "model" / "metrics_world.json").read_text())
    assert unseen["num_examples"] == windows and unseen["copy_acc"] == metrics["copy_acc"]
    assert json.loads((tmp_path / "model" / "metrics_rollout_world.json").read_text())["stall_ratio"] == 0.4
    assert not list((tmp_path / "model").glob("metrics*none*")) and not list((tmp_path / "model").glob("*unseen*"))
    state = saved_training_state(tmp_path / "model")
    assert (state["trainer"]["args"]["max_train_steps"], state["trainer"]["args"]["num_warmup_steps"]) == (40, 2)
    groups = state["optimizer"]["param_groups"]
    assert {g["initial_lr"] for g in groups} == {3e-3}  # the recipe's learning rate, not the main command's
    assert {g["weight_decay"] for g in groups} == {0.0, 0.1}  # WEIGHT_DECAY reaches train.py through run_sample.sh
    assert state["trainer"]["args"]["no_compile"]  # eager unless COMPILE=1

    # SKIP_BUILD=1: the world copied without its frames (raw/) trains as it is, after a check against its manifests
    copied = tmp_path / "copied"
    for split in ("train", "val"):
        shutil.copytree(tmp_path / "world" / split, copied / split)
    env.update(GPU_DIR=str(copied), OUT=str(tmp_path / "model2"), SKIP_BUILD="1", STEPS="2", COMPILE="1")
    subprocess.run(["bash", str(REPO / "run_gpu.sh"), "--per_device_train_batch_size", "1",
                    "--eval_every_n_steps", "0"], cwd=REPO, env=env, check=True, timeout=600)
    assert (tmp_path / "model2" / "final_checkpt" / "model.safetensors").is_file()
    assert not saved_training_state(tmp_path / "model2")["trainer"]["args"]["no_compile"]  # COMPILE=1
    assert not (copied / "raw").exists()  # nothing rendered again

    with open(copied / "val" / "video.bin", "r+b") as f:  # a copy cut short
        f.truncate(f.seek(0, 2) - 512)
    broken = subprocess.run(["bash", str(REPO / "run_gpu.sh")], cwd=REPO, env=env, capture_output=True, text=True,
                            timeout=120)
    assert broken.returncode == 1 and "video.bin" in broken.stderr and "copy it again" in broken.stderr
    shutil.rmtree(copied / "train")
    missing = subprocess.run(["bash", str(REPO / "run_gpu.sh")], cwd=REPO, env=env, capture_output=True, text=True,
                             timeout=120)
    assert missing.returncode == 1 and f"{copied / 'train' / 'metadata.json'} is missing" in missing.stderr
