"""CUDA: what the CPU suite cannot show. Skipped on a machine without a CUDA GPU.

The suite hides CUDA (tests/conftest.py), so each test here runs its work in a subprocess that sees the GPU again
(the CUDA_VISIBLE_DEVICES value found when pytest started). CUDA's guarantees differ from the CPU's: cached and
recomputed evaluation agree to bf16 tolerance, and a resumed run matches an uninterrupted one within float noise,
not bit for bit.

GENIE_CUDA_TESTS_DEVICE=cpu runs the same tests on the CPU (to check the tests themselves on a machine without a
GPU); torch.compile on the CPU needs a C++ compiler.
"""
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file

from common.train_state import COMPLETE_MARKER, list_checkpoints
from tests.test_train import make_token_dataset, train_argv, write_config

REPO = Path(__file__).resolve().parents[1]
DEVICE = os.environ.get("GENIE_CUDA_TESTS_DEVICE", "cuda")


def device_env() -> dict:
    """The environment of the subprocesses: the GPU visible again (or, on the CPU, still hidden)."""
    env = dict(os.environ)
    if DEVICE == "cuda":
        original = env.get("GENIE_TEST_CUDA_VISIBLE_DEVICES", "unset")
        if original == "unset":
            env.pop("CUDA_VISIBLE_DEVICES", None)
        else:
            env["CUDA_VISIBLE_DEVICES"] = original
    return env


def cuda_available() -> bool:
    if DEVICE != "cuda":
        return True
    if shutil.which("nvidia-smi") is None and not Path("/dev/nvidia0").exists():
        return False  # no driver: skip without starting a Python that imports torch
    probe = "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"
    return subprocess.run([sys.executable, "-c", probe], env=device_env(), timeout=120).returncode == 0


pytestmark = pytest.mark.skipif(not cuda_available(), reason="no CUDA GPU")


def run_python(code: str, timeout: int = 600) -> str:
    """Run a Python snippet on the device (the name DEVICE is defined for it); returns its output."""
    proc = subprocess.run([sys.executable, "-c", f"DEVICE = {DEVICE!r}\n" + textwrap.dedent(code)], cwd=REPO,
                          env=device_env(), capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout


def run_script(args, timeout: int = 600) -> str:
    proc = subprocess.run([sys.executable, *map(str, args)], cwd=REPO, env=device_env(), capture_output=True,
                          text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout + proc.stderr


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("cuda_data")
    return {"train": make_token_dataset(root / "train", [8] * 12, seed=0),
            "val": make_token_dataset(root / "val", [8] * 3, seed=1),
            "config": write_config(root / "tiny.json")}


def test_cached_inference_equals_recomputation_on_the_device():
    """fp32: identical samples; bf16 autocast: first-step logits within bf16 tolerance, nearly all samples equal."""
    run_python("""
        import torch
        from genie import GenieConfig, STMaskGIT
        from genie.inference import generate_frames, teacher_forced
        from genie.reference import generate_uncached, teacher_forced_uncached

        torch.manual_seed(0)
        config = GenieConfig(num_layers=2, num_heads=4, d_model=64, T=6, S=16, image_vocab_size=64 ** 2, qk_norm=True,
                             num_prompt_frames=2)
        model = STMaskGIT(config)
        model.init_weights()
        with torch.no_grad():
            model.out_x_proj.weight.normal_(0, 1.0)
        model = model.to(DEVICE).eval()
        x = torch.randint(0, config.image_vocab_size, (4, 6, 4, 4), device=DEVICE)

        def gen(seed):
            return torch.Generator(device=DEVICE).manual_seed(seed)

        cached = generate_frames(model, x[:, :2], 4, 2, 1.0, generator=gen(3))
        full = generate_uncached(model, x[:, :2], 4, 2, 1.0, generator=gen(3))
        assert torch.equal(cached[0], full[0])
        torch.testing.assert_close(cached[1], full[1], atol=1e-4, rtol=1e-4)

        with torch.autocast(DEVICE, dtype=torch.bfloat16):
            cached = teacher_forced(model, x, 2, 0.0, generator=gen(7))
            full = teacher_forced_uncached(model, x, 2, 0.0, generator=gen(7))
        torch.testing.assert_close(cached[1].float(), full[1].float(), atol=0.1, rtol=0.05)
        assert (cached[0] == full[0]).float().mean() > 0.95
    """)


@pytest.mark.parametrize("compile_flag", ["--no_compile", "--compile"])
def test_train_steps_in_bf16(data, tmp_path, compile_flag):
    out = run_script(["train.py", *train_argv(data, tmp_path, "--max_train_steps", "3", "--checkpointing_steps",
                                              "2", "--mixed_precision", "bf16", compile_flag)])
    assert "training 3 steps" in out
    weights = load_file(str(tmp_path / "final_checkpt" / "model.safetensors"))
    assert all(torch.isfinite(w).all() for w in weights.values())
    assert [step for step, _ in list_checkpoints(tmp_path)] == [2, 3]


def test_sigterm_then_resume_on_the_device(data, tmp_path):
    out_dir = tmp_path / "run"
    args = train_argv(data, out_dir, "--max_train_steps", "12", "--checkpointing_steps", "4",
                      "--mixed_precision", "bf16", "--no_compile", "--debug_step_sleep", "0.25")
    with open(tmp_path / "run.log", "w") as log:
        proc = subprocess.Popen([sys.executable, "train.py", *args], cwd=REPO, env=device_env(), stdout=log,
                                stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 300
    while not (out_dir / "checkpoint-4" / COMPLETE_MARKER).exists():
        assert proc.poll() is None and time.monotonic() < deadline, (tmp_path / "run.log").read_text()
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=300) == 0, (tmp_path / "run.log").read_text()
    assert not (out_dir / "final_checkpt").exists()
    stopped_at = list_checkpoints(out_dir)[-1][0]
    assert 4 <= stopped_at < 12
    resumed = run_script(["train.py", *train_argv(data, out_dir, "--max_train_steps", "12", "--checkpointing_steps",
                                                  "4", "--mixed_precision", "bf16", "--no_compile",
                                                  "--resume_from_checkpoint", "latest")])
    assert f"at step {stopped_at}" in resumed
    weights = load_file(str(out_dir / "final_checkpt" / "model.safetensors"))
    assert all(torch.isfinite(w).all() for w in weights.values())


def test_evaluate_and_generate_on_the_device(data, tmp_path):
    run_script(["train.py", *train_argv(data, tmp_path / "model", "--max_train_steps", "2", "--checkpointing_steps",
                                        "0", "--no_compile")])
    ckpt = tmp_path / "model" / "final_checkpt"
    out = run_script(["evaluate.py", "--checkpoint_dir", ckpt, "--val_data_dir", data["val"], "--window_size", "4",
                      "--stride", "1", "--skip_lpips", "--device", DEVICE])
    assert '"acc"' in out and '"loss"' in out
    run_script(["generate.py", "--checkpoint_dir", ckpt, "--val_data_dir", data["val"], "--output_dir",
                tmp_path / "generated", "--window_size", "4", "--stride", "1", "--num_prompt_frames", "2",
                "--num_examples", "2", "--device", DEVICE])
    assert (tmp_path / "generated" / "video.bin").is_file()


def test_motion_estimator_trains_on_the_device_and_loads_on_the_cpu(tmp_path):
    run_python(f"""
        import numpy as np
        from sample_world.motion_estimator import load_motion_estimator, train_motion_estimator

        rng = np.random.default_rng(0)
        np.savez("{tmp_path}/train.npz", frames=rng.integers(0, 256, size=(40, 64, 64, 3), dtype=np.uint8),
                 poses=rng.normal(size=(40, 3)).astype(np.float32), segment_ids=np.zeros(40, np.int64))
        net = train_motion_estimator("{tmp_path}/train.npz", "{tmp_path}/est.safetensors", steps=3, progress=False,
                                     device=DEVICE)
        assert next(net.parameters()).device.type == "cpu"
        frames = rng.integers(0, 256, size=(3, 64, 64, 3), dtype=np.uint8)
        assert np.allclose(load_motion_estimator("{tmp_path}/est.safetensors").motion(frames), net.motion(frames))
    """)
