"""The benchmark scripts still run (tiny shapes): they are how speed claims in the README are reproduced."""
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
# bench_train.py at a shape that runs in about a second: one timed step of a 1-layer model, no warm-up
TINY_TRAIN_STEP = ["--num_layers", "1", "--d_model", "32", "--num_heads", "2", "--s", "4", "--T", "10",
                   "--image_vocab_size", "4096", "--steps", "1", "--warmup_steps", "0"]


def load(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("script", sorted(p.name for p in BENCHMARKS.glob("bench_*.py")))
def test_benchmark_scripts_start_from_any_directory(script, tmp_path):
    """Run as `python benchmarks/X.py`, a script sees only its own folder and the installed packages."""
    done = subprocess.run([sys.executable, str(BENCHMARKS / script), "--help"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr


def test_bench_train_compare_runs_fp32_and_both_bf16_attention_paths(capsys):
    from genie.transformer import SelfAttention
    load("bench_train").main([*TINY_TRAIN_STEP, "--mixed_precision", "compare"])
    out = capsys.readouterr().out
    assert "fp32:" in out and "bf16 (fused attention):" in out and "bf16 (written-out temporal attention):" in out
    assert "bf16 (written-out temporal attention) vs fp32:" in out
    # the comparison sets the path per model, no global state: a fresh attention layer is on the default path
    assert SelfAttention(d_model=8, num_heads=2).cpu_bf16_math


def test_bench_train_readout_compare_runs_both_readouts(capsys):
    load("bench_train").main([*TINY_TRAIN_STEP, "--readout", "compare"])
    out = capsys.readouterr().out
    assert "fp32, all logits:" in out and "masked-token readout vs all logits:" in out


def test_bench_train_optimizer_compare_steps_both_optimizers(capsys):
    load("bench_train").main([*TINY_TRAIN_STEP, "--optimizer", "compare"])
    out = capsys.readouterr().out
    assert "fp32:" in out and "fp32, Muon + AdamW:" in out and "Muon + AdamW vs AdamW:" in out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="page faults are counted on Linux")
def test_bench_allocator_times_both_allocators_each_in_its_own_process(capsys):
    load("bench_allocator").main([*TINY_TRAIN_STEP, "--rounds", "1"])
    out = capsys.readouterr().out
    assert out.count("default:") == 1 and out.count("retain:") == 1
    assert out.count("minor page faults per step") == 2 and "train: retained memory vs glibc's defaults:" in out


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="page faults are counted on Linux")
def test_bench_allocator_tokenizes_frames_under_both_allocators(capsys, tmp_path):
    frames = tmp_path / "frames.npz"
    np.savez(frames, frames=np.random.default_rng(0).integers(0, 256, (4, 64, 64, 3), dtype=np.uint8))
    load("bench_allocator").main(["--workload", "tokenize", "--frames", str(frames), "--rounds", "1"])
    out = capsys.readouterr().out
    assert out.count("minor page faults") == 2 and "tokenize: retained memory vs glibc's defaults:" in out


def test_bench_allocator_needs_frames_to_tokenize(capsys, tmp_path):
    with pytest.raises(SystemExit):
        load("bench_allocator").main(["--workload", "tokenize", "--frames", str(tmp_path / "missing.npz")])
    assert "needs --frames" in capsys.readouterr().err


def test_bench_copy_head_times_three_mixtures_that_agree(capsys):
    load("bench_copy_head").main(["--num_tokens", "16", "--d_model", "8", "--repeats", "1", "--radius", "1"])
    out = capsys.readouterr().out
    assert "K 9 neighbours" in out and out.count("sparse/plain") == 2 and "joint/factor-wise" in out
    assert "best-neighbour/joint" in out and "without/with the mode" in out
    assert float(out.rsplit("log-probability:", 1)[1]) < 1e-4  # the sparse mixture equals the dense one


def test_bench_train_takes_a_genie_config_with_a_copy_head(tmp_path, capsys):
    config = {"num_layers": 1, "num_heads": 2, "d_model": 32, "T": 4, "S": 16, "image_vocab_size": 4096,
              "num_prompt_frames": 2, "copy_radius": 1, "copy_match_input": True}
    (tmp_path / "config.json").write_text(json.dumps(config))
    load("bench_train").main(["--genie_config", str(tmp_path / "config.json"), "--steps", "1", "--warmup_steps", "0"])
    out = capsys.readouterr().out
    assert "STMaskGIT 1 layers, d_model 32, T 4, 4x4" in out and "fp32:" in out


def test_bench_train_runs_an_action_config_under_its_training_recipe(tmp_path, capsys, monkeypatch):
    from genie.model import STMaskGIT
    config = {"num_layers": 1, "num_heads": 2, "d_model": 32, "T": 4, "S": 16, "image_vocab_size": 4096,
              "num_prompt_frames": 2, "copy_radius": 1, "copy_match_input": True, "self_reveal_ratio": 1.0,
              "action_names": ["buttons", "driving_command"], "action_dim": 5, "num_latent_actions": 3}
    (tmp_path / "config.json").write_text(json.dumps(config))
    ratios = []
    real_reveal = STMaskGIT._reveal_own_predictions
    monkeypatch.setattr(STMaskGIT, "_reveal_own_predictions", lambda model, x, cond, ratio: ratios.append(ratio) or
                        real_reveal(model, x, cond, ratio))
    bench = load("bench_train")
    bench.main(["--genie_config", str(tmp_path / "config.json"), "--steps", "1", "--warmup_steps", "0"])
    assert "fp32:" in capsys.readouterr().out
    assert ratios and all(r == 1.0 for r in ratios)  # the config's self_reveal_ratio, as train.py uses it
    ratios.clear()
    bench.main(["--genie_config", str(tmp_path / "config.json"), "--steps", "1", "--warmup_steps", "0",
                "--recipe", "published"])
    assert not ratios  # the published recipe reveals nothing


def test_bench_play_serves_steps_and_compares_the_cached_step(tmp_path, capsys):
    from tests.play_fixtures import tiny_dataset, tiny_model, tiny_tokenizer

    data = tiny_dataset(tmp_path / "val", tiny_tokenizer(tmp_path / "tokenizer"))
    load("bench_play").main(["--checkpoint_dir", str(tiny_model(tmp_path / "model")), "--data_dir", str(data),
                             "--steps", "3", "--warmup", "1", "--model_steps", "6", "--num_threads", "1",
                             "--browser_seconds", "2"])
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["http_steps_per_second"] > 0 and not result["real_world"]
    has_browser = shutil.which("chromium") and shutil.which("chromedriver") and importlib.util.find_spec("selenium")
    if has_browser:  # the page walked with the keys held (a new key every second)
        assert result["page"]["steps"] > 0 and result["page"]["steps_per_second"] > 0
        assert result["page"]["page_readout"] > 0
    else:
        assert result["page"] is None
    model = result["model_step"]  # T = 4: the context restarts every 2 steps
    assert {"cached", "restart", "per_step_ms", "sliding_ms", "speedup_over_sliding", "same_tokens"} == set(model)
    assert model["cached"]["steps"] + model["restart"]["steps"] == 6 and model["restart"]["steps"] >= 2
    assert all(model[phase]["speedup"] > 0 for phase in ("cached", "restart")) and model["speedup_over_sliding"] > 0
    assert result["model_step"]["same_tokens"] == 1.0  # the tiny model has no near-ties
