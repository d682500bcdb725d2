"""Crash safety of train.py: SIGKILL + resume equality, SIGTERM checkpoint, non-finite guard, 2-process DDP,
and the atomic / safe serialization helpers in common/train_state.py."""
import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import train
from genie import GenieConfig, STMaskGIT
from common.files import remove_stale_temp_dirs
from common.train_state import (COMPLETE_MARKER, TrainingStateError, atomic_directory, capture_rng_state,
                               list_checkpoints, load_state_files, load_training_checkpoint, resolve_resume_path,
                               restore_rng_state, save_state_files)
from tests.test_train import (assert_same_weights, load_weights, make_token_dataset, masked_val_loss, train_argv,
                              write_config)

REPO = Path(__file__).resolve().parents[1]
# 12 steps of 2 micro-batches of 2 windows, checkpoints every 4 steps, validation in between (it must not disturb
# the training RNG streams).
RUN_ARGS = ("--max_train_steps", "12", "--checkpointing_steps", "4", "--checkpoints_total_limit", "0",
            "--per_device_train_batch_size", "2", "--gradient_accumulation_steps", "2", "--eval_every_n_steps", "5")


pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("reliability_data")
    return {"train": make_token_dataset(root / "train", [8] * 12, seed=0),
            "val": make_token_dataset(root / "val", [8] * 3, seed=1),
            "config": write_config(root / "tiny.json")}


def start(cmd, log_path, cwd) -> subprocess.Popen:
    """Start a CPU training subprocess, output to a file (a full pipe would block it)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    with open(log_path, "w") as log:  # the child keeps its own copy of the descriptor
        return subprocess.Popen(cmd, cwd=cwd, env=env, stdout=log, stderr=subprocess.STDOUT)


def start_train(data, output_dir, *extra) -> subprocess.Popen:
    output_dir.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, str(REPO / "train.py"), *train_argv(data, output_dir, *RUN_ARGS, *extra)]
    return start(cmd, output_dir.parent / f"{output_dir.name}.log", output_dir.parent)


def finish(proc: subprocess.Popen, timeout=120) -> int:
    return proc.wait(timeout=timeout)


def wait_for(predicate, proc, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not predicate():
        assert proc.poll() is None, f"training exited early with code {proc.returncode}"
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def log_of(output_dir: Path) -> str:
    return (output_dir.parent / f"{output_dir.name}.log").read_text()


@pytest.fixture(scope="module")
def reference(data, tmp_path_factory):
    """An uninterrupted run, started once for the module (it runs while the interrupted runs start up)."""
    out = tmp_path_factory.mktemp("reference") / "run"
    proc = start_train(data, out)

    def final_weights():
        assert finish(proc) == 0, log_of(out)
        return load_weights(out / "final_checkpt")
    return final_weights


def test_sigkill_then_resume_matches_uninterrupted_run_bit_for_bit(data, reference, tmp_path):
    out = tmp_path / "run"
    proc = start_train(data, out, "--debug_step_sleep", "0.25")
    wait_for(lambda: (out / "checkpoint-4" / COMPLETE_MARKER).exists(), proc)
    time.sleep(random.uniform(0.0, 0.6))  # anywhere in the next steps, possibly while checkpoint-8 is written
    proc.send_signal(signal.SIGKILL)
    finish(proc)
    assert not (out / "final_checkpt").exists(), "the run finished before it was killed"
    resumed_from = list_checkpoints(out)[-1][0]

    assert finish(start_train(data, out, "--resume_from_checkpoint", "latest")) == 0, log_of(out)
    assert f"resumed from {out / f'checkpoint-{resumed_from}'} at step {resumed_from}" in log_of(out)
    assert_same_weights(reference(), load_weights(out / "final_checkpt"))
    assert not [p for p in out.iterdir() if p.name.startswith(".tmp-")]  # leftovers of the kill are cleaned


def test_sigterm_saves_a_checkpoint_and_exits_cleanly(data, reference, tmp_path):
    out = tmp_path / "run"
    proc = start_train(data, out, "--debug_step_sleep", "0.25")
    wait_for(lambda: (out / "checkpoint-4" / COMPLETE_MARKER).exists(), proc)
    proc.send_signal(signal.SIGTERM)
    assert finish(proc) == 0, log_of(out)
    assert "SIGTERM" in log_of(out)
    assert not (out / "final_checkpt").exists()
    stopped_at = list_checkpoints(out)[-1][0]
    assert 4 < stopped_at < 12  # a checkpoint of the step where it stopped, not just the periodic one

    assert finish(start_train(data, out, "--resume_from_checkpoint", "latest")) == 0, log_of(out)
    assert_same_weights(reference(), load_weights(out / "final_checkpt"))


def test_a_nonfinite_step_is_skipped(data, tmp_path, caplog):
    train.main(train_argv(data, tmp_path, "--max_train_steps", "3", "--checkpointing_steps", "1",
                          "--checkpoints_total_limit", "0", "--debug_inject_nan_at_steps", "2"))
    assert "step 2: non-finite loss" in caplog.text
    assert_same_weights(load_weights(tmp_path / "checkpoint-1"), load_weights(tmp_path / "checkpoint-2"))
    after = load_weights(tmp_path / "checkpoint-3")
    assert all(torch.isfinite(v).all() for v in after.values())
    assert not torch.equal(after["out_x_proj.weight"], load_weights(tmp_path / "checkpoint-2")["out_x_proj.weight"])


def test_too_many_nonfinite_steps_stop_with_the_last_good_state_saved(data, tmp_path):
    train.main(train_argv(data, tmp_path / "one_step", "--max_train_steps", "1", "--checkpointing_steps", "1"))
    with pytest.raises(SystemExit, match="3 optimizer steps in a row had a NaN/inf loss"):
        train.main(train_argv(data, tmp_path / "run", "--max_train_steps", "10", "--checkpointing_steps", "100",
                              "--max_nonfinite_steps", "3", "--debug_inject_nan_at_steps", "2", "3", "4"))
    assert [step for step, _ in list_checkpoints(tmp_path / "run")] == [4]
    assert not (tmp_path / "run" / "final_checkpt").exists()
    assert_same_weights(load_weights(tmp_path / "one_step" / "final_checkpt"),
                        load_weights(tmp_path / "run" / "checkpoint-4"))
    good = load_training_checkpoint(tmp_path / "one_step" / "checkpoint-1")["optimizer"]["state"]
    saved = load_training_checkpoint(tmp_path / "run" / "checkpoint-4")["optimizer"]["state"]
    for a, b in zip(good.values(), saved.values()):
        assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_diverged_run_stops_without_saving_its_weights(data, tmp_path):
    """A learning rate far too high sends the loss past twice a uniform guess's and keeps it there: the run stops
    within --max_diverged_steps of it, names the last checkpoint, and leaves no final model."""
    with pytest.raises(SystemExit, match=r"training diverged: the loss stayed above 16\.6 .* from step \d+ to step "
                                         r"\d+ .*the last checkpoint is .*checkpoint-\d+"):
        train.main(train_argv(data, tmp_path / "run", "--max_train_steps", "40", "--checkpointing_steps", "1",
                              "--optimizer", "adamw", "--learning_rate", "0.1", "--max_diverged_steps", "4"))
    steps = [step for step, _ in list_checkpoints(tmp_path / "run")]
    assert steps and steps[-1] < 40 and not (tmp_path / "run" / "final_checkpt").exists()
    # a healthy run never trips it, not even at a limit of one step
    train.main(train_argv(data, tmp_path / "healthy", "--max_train_steps", "6", "--max_diverged_steps", "1"))
    assert (tmp_path / "healthy" / "final_checkpt" / "model.safetensors").exists()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_process_ddp_training_and_single_process_resume(data, tmp_path):
    out = tmp_path / "ddp"
    out.mkdir()
    cmd = [sys.executable, "-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes", "2",
           "--num_machines", "1", "--mixed_precision", "no", "--dynamo_backend", "no",
           "--main_process_port", str(free_port()), str(REPO / "train.py"),
           *train_argv(data, out, "--max_train_steps", "16", "--checkpointing_steps", "8",
                       "--checkpoints_total_limit", "0", "--per_device_train_batch_size", "2",
                       "--eval_every_n_steps", "8")]
    assert finish(start(cmd, tmp_path / "ddp.log", tmp_path)) == 0, (tmp_path / "ddp.log").read_text()
    log = (tmp_path / "ddp.log").read_text()
    assert "2 processes" in log and log.count("saved the final model") == 1  # only the main process writes

    ckpt = load_training_checkpoint(out / "checkpoint-16")
    assert ckpt["trainer"]["world_size"] == 2 and len(ckpt["rng"]) == 2
    config = GenieConfig.from_pretrained(data["config"])
    torch.manual_seed(0)
    untrained = STMaskGIT(config)
    untrained.init_weights()
    trained = STMaskGIT.from_pretrained(out / "final_checkpt")
    assert masked_val_loss(trained, data["val"], config) < 0.8 * masked_val_loss(untrained, data["val"], config)

    train.main(train_argv(data, tmp_path / "single", "--max_train_steps", "18", "--checkpointing_steps", "0",
                          "--resume_from_checkpoint", str(out / "checkpoint-16")))
    assert (tmp_path / "single" / "final_checkpt" / "model.safetensors").is_file()


# ---------------------------------------------------------------- common/train_state.py helpers

def test_atomic_directory_never_leaves_a_partial_directory(tmp_path):
    target = tmp_path / "checkpoint-1"
    with pytest.raises(RuntimeError):
        with atomic_directory(target) as tmp:
            (tmp / "model.safetensors").write_bytes(b"half")
            raise RuntimeError("killed")
    assert not target.exists() and list(tmp_path.iterdir()) == []

    with atomic_directory(target) as tmp:
        (tmp / "a").write_text("old")
    with atomic_directory(target) as tmp:
        (tmp / "b").write_text("new")
    assert sorted(p.name for p in target.iterdir()) == [COMPLETE_MARKER, "MANIFEST.json", "b"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint-1"]

    (tmp_path / ".tmp-checkpoint-2.123").mkdir()
    remove_stale_temp_dirs(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint-1"]


def test_resume_path_resolution(tmp_path):
    assert resolve_resume_path(tmp_path, "latest") is None  # nothing yet: start fresh
    for step in (3, 12):
        with atomic_directory(tmp_path / f"checkpoint-{step}"):
            pass
    (tmp_path / "checkpoint-20").mkdir()  # killed while writing (no marker)
    assert resolve_resume_path(tmp_path, "latest") == tmp_path / "checkpoint-12"
    assert resolve_resume_path(tmp_path, str(tmp_path / "checkpoint-3")) == tmp_path / "checkpoint-3"
    with pytest.raises(TrainingStateError, match="incomplete"):
        resolve_resume_path(tmp_path, str(tmp_path / "checkpoint-20"))
    with pytest.raises(TrainingStateError, match="no such directory"):
        resolve_resume_path(tmp_path, str(tmp_path / "checkpoint-99"))


def test_optimizer_state_round_trips_through_safetensors_and_json(tmp_path):
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.LayerNorm(4))
    opt = torch.optim.AdamW([{"params": model[0].parameters(), "weight_decay": 0.1},
                             {"params": model[1].parameters(), "weight_decay": 0.0}], lr=1e-3, betas=(0.8, 0.95))
    model(torch.randn(2, 3)).sum().backward()
    opt.step()
    save_state_files(tmp_path, "optimizer", opt.state_dict())
    assert not list(tmp_path.glob("*.pt")) and not list(tmp_path.glob("*.pkl"))
    loaded = load_state_files(tmp_path, "optimizer")
    assert loaded["param_groups"] == opt.state_dict()["param_groups"]
    for pid, state in opt.state_dict()["state"].items():
        assert all(torch.equal(state[k], loaded["state"][pid][k]) for k in state)
    opt2 = torch.optim.AdamW([{"params": model[0].parameters()}, {"params": model[1].parameters()}], lr=0.5)
    opt2.load_state_dict(loaded)
    assert opt2.param_groups[0]["betas"] == (0.8, 0.95) and opt2.param_groups[0]["lr"] == 1e-3

    (tmp_path / "optimizer.json").write_text("{not json")
    with pytest.raises(TrainingStateError, match="optimizer.json"):
        load_state_files(tmp_path, "optimizer")


def test_rng_state_round_trip(tmp_path):
    state = capture_rng_state()
    save_state_files(tmp_path, "rng", [state])
    first = (torch.rand(3), np.random.rand(3), random.random())
    restore_rng_state(load_state_files(tmp_path, "rng")[0])
    second = (torch.rand(3), np.random.rand(3), random.random())
    assert torch.equal(first[0], second[0]) and np.array_equal(first[1], second[1]) and first[2] == second[2]
