"""generate.py: output layout (prompt | predictions | ground truth), modes, determinism, clear errors."""
import json
import re

import numpy as np
import pytest
import torch

from common.cli import run_main
from data import RawTokenDataset, read_metadata
import generate as generate  # the script module (generate, the function, is genie.inference.generate_frames)
from genie import GenieConfig, STMaskGIT
from tests.test_train import TINY, make_token_dataset

T, P, S_SIDE = TINY["T"], 2, 4  # window 4 frames, 2 prompt frames, 4x4 tokens


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("generate")
    make_token_dataset(root / "val", [8, 6, 9], seed=2)
    torch.manual_seed(0)
    model = STMaskGIT(GenieConfig(**TINY))
    model.init_weights()
    model.save_pretrained(root / "ckpt")
    return root


def run(setup, out, *extra):
    generate.main(["--val_data_dir", str(setup / "val"), "--checkpoint_dir", str(setup / "ckpt"),
                   "--output_dir", str(out), "--window_size", str(T), "--num_prompt_frames", str(P),
                   "--stride", "1", "--device", "cpu", *extra])


def run_script(argv, capsys) -> str:
    """generate.py's main as the script runs it, for bad input: status 1 and one error line, returned."""
    assert run_main("generate.py", generate.main, argv) == 1
    err = capsys.readouterr().err
    assert "Traceback" not in err
    line = err.strip().splitlines()[-1]
    assert line.startswith("generate.py: error: ")
    return line


def read_examples(out):
    meta = read_metadata(out)
    video = np.fromfile(out / "video.bin", dtype=meta["token_dtype"])
    frames = 2 * meta["window_size"] - meta["num_prompt_frames"]
    return meta, video.reshape(meta["num_examples"], frames, S_SIDE, S_SIDE).astype(np.int64)


def ground_truth(setup, indices):
    ds = RawTokenDataset(setup / "val", window_size=T, stride=1)
    return np.stack([ds[i]["tokens"].numpy() for i in indices])


def test_output_layout(setup, tmp_path):
    run(setup, tmp_path, "--example_ind", "3", "--num_examples", "5", "--batch_size", "2")
    meta, examples = read_examples(tmp_path)
    assert meta["num_images"] == 5 * (2 * T - P) and meta["s"] == S_SIDE
    assert meta["num_prompt_frames"] == P and meta["window_size"] == T
    assert meta["tokenizer_ckpt"] == "data/tiny_tokenizer"  # carried over for visualize.py
    assert (tmp_path / "video.bin").stat().st_size == meta["num_images"] * S_SIDE ** 2 * 4
    gt = ground_truth(setup, range(3, 8))
    np.testing.assert_array_equal(examples[:, :P], gt[:, :P])  # prompt
    np.testing.assert_array_equal(examples[:, T:], gt[:, P:])  # ground truth
    predictions = examples[:, P:T]
    assert predictions.min() >= 0 and predictions.max() < TINY["image_vocab_size"]  # every mask filled
    # The output is itself a token dataset: one segment per example, so windows never mix two examples.
    windows = RawTokenDataset(tmp_path, window_size=2 * T - P, stride=1)
    assert len(windows) == 5
    np.testing.assert_array_equal(windows[4]["tokens"].numpy(), examples[4])


def test_teacher_forcing_predicts_each_frame_from_ground_truth(setup, tmp_path):
    """One greedy MaskGIT step is deterministic: with teacher forcing, frame t is what plain generation predicts
    from a prompt of the t ground-truth frames before it."""
    greedy = ("--maskgit_steps", "1", "--temperature", "0", "--example_ind", "1", "--num_examples", "3")
    run(setup, tmp_path / "tf", *greedy, "--teacher_force_time")
    _, tf = read_examples(tmp_path / "tf")
    for t in range(P, T):
        generate.main(["--val_data_dir", str(setup / "val"), "--checkpoint_dir", str(setup / "ckpt"),
                       "--output_dir", str(tmp_path / f"p{t}"), "--window_size", str(T), "--num_prompt_frames",
                       str(t), "--stride", "1", "--device", "cpu", *greedy])
        _, ar = read_examples(tmp_path / f"p{t}")
        np.testing.assert_array_equal(tf[:, t], ar[:, t])


def test_sampling_is_reproducible_with_a_seed(setup, tmp_path):
    sampled = ("--temperature", "1.0", "--maskgit_steps", "3", "--num_examples", "4")
    run(setup, tmp_path / "a", *sampled, "--seed", "5")
    run(setup, tmp_path / "b", *sampled, "--seed", "5")
    run(setup, tmp_path / "c", *sampled, "--seed", "6")
    a, b, c = (read_examples(tmp_path / k)[1] for k in "abc")
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


@pytest.mark.parametrize("make_bad,pattern", [
    (lambda root: make_token_dataset(root / "data", [8], s=8), r"data/metadata.json: frames are 8x8 .* S=16"),
    (lambda root: make_token_dataset(root / "data", [8], vocab_size=1024, num_distinct=4),
     r"vocab_size 1024 differs .* 4096"),
])
def test_data_checkpoint_mismatch_is_a_clear_error(setup, tmp_path, capsys, make_bad, pattern):
    make_bad(tmp_path)
    assert re.search(pattern, run_script(["--val_data_dir", str(tmp_path / "data"), "--checkpoint_dir",
                                          str(setup / "ckpt"), "--output_dir", str(tmp_path / "out"), "--window_size",
                                          str(T), "--num_prompt_frames", str(P), "--stride", "1", "--device", "cpu"],
                                         capsys))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("extra,pattern", [
    (("--window_size", "3"), r"--window_size 3 must equal the model's T=4 \(checkpoint .*ckpt\)"),
    (("--example_ind", "9", "--num_examples", "10"), r"examples 9..18 requested but the dataset has 14 windows"),
    (("--copy_bias", "1"), r"--copy_bias: the checkpoint .*ckpt has no copy head"),
])
def test_argument_errors(setup, tmp_path, capsys, extra, pattern):
    assert re.search(pattern, run_script(["--val_data_dir", str(setup / "val"), "--checkpoint_dir",
                                          str(setup / "ckpt"), "--output_dir", str(tmp_path), "--window_size", str(T),
                                          "--num_prompt_frames", str(P), "--stride", "1", "--device", "cpu", *extra],
                                         capsys))


@pytest.mark.parametrize("missing", ["checkpoint", "data"])
def test_missing_inputs(setup, tmp_path, capsys, missing):
    paths = {"checkpoint": setup / "ckpt", "data": setup / "val", missing: tmp_path / "not_there"}
    assert "not_there" in run_script(["--val_data_dir", str(paths["data"]), "--checkpoint_dir",
                                      str(paths["checkpoint"]), "--output_dir", str(tmp_path / "out"),
                                      "--window_size", str(T), "--num_prompt_frames", str(P), "--device", "cpu"],
                                     capsys)


def test_metadata_is_valid_json_with_generation_settings(setup, tmp_path):
    run(setup, tmp_path, "--maskgit_steps", "3", "--temperature", "0.5", "--unmask_mode", "greedy")
    meta = json.loads((tmp_path / "metadata.json").read_text())
    assert (meta["maskgit_steps"], meta["temperature"], meta["unmask_mode"]) == (3, 0.5, "greedy")
    assert meta["frames_per_example"] == 2 * T - P and meta["num_examples"] == 1


@pytest.mark.parametrize("choice", ["joint", "best_neighbour"])
def test_greedy_tokens_reach_a_copy_model_and_its_metadata(setup, tmp_path, monkeypatch, choice):
    torch.manual_seed(0)
    model = STMaskGIT(GenieConfig(**TINY, copy_radius=1))
    model.init_weights()
    model.save_pretrained(tmp_path / "copy_ckpt")
    settings = []
    real = STMaskGIT.set_decoding
    monkeypatch.setattr(STMaskGIT, "set_decoding",
                        lambda m, value: settings.append(value.greedy_tokens) or real(m, value))
    generate.main(["--val_data_dir", str(setup / "val"), "--checkpoint_dir", str(tmp_path / "copy_ckpt"),
                   "--output_dir", str(tmp_path / "out"), "--window_size", str(T), "--num_prompt_frames", str(P),
                   "--stride", "1", "--device", "cpu", "--greedy_tokens", choice, "--copy_bias", "2"])
    assert settings[-1] == choice
    meta = read_metadata(tmp_path / "out")
    assert (meta["greedy_tokens"], meta["copy_bias"]) == (choice, 2.0)


def test_stall_ratio_reaches_generation_and_metadata(setup, tmp_path, monkeypatch):
    seen = []
    real = generate.generate_frames
    monkeypatch.setattr(generate, "generate_frames",
                        lambda *a, **kw: seen.append(kw["stall_ratio"]) or real(*a, **kw))
    run(setup, tmp_path, "--stall_ratio", "0.4", "--num_examples", "2")
    assert seen == [0.4]
    assert read_metadata(tmp_path)["stall_ratio"] == 0.4
    run(setup, tmp_path / "off")
    assert seen == [0.4, None] and read_metadata(tmp_path / "off")["stall_ratio"] is None


@pytest.mark.parametrize("extra, pattern", [
    (("--stall_ratio", "0"), r"expected a number in \(0, 1\], got 0"),
    (("--stall_ratio", "1.5"), r"expected a number in \(0, 1\], got 1.5"),
    (("--stall_ratio", "half"), r"expected a number in \(0, 1\], got 'half'"),
    (("--stall_ratio", "0.4", "--teacher_force_time"), "ground truth, which never stalls"),
    (("--stall_ratio", "0.4", "--num_prompt_frames", "1"), "needs --num_prompt_frames >= 2, got 1"),
    (("--greedy_tokens", "factored"), "argument --greedy_tokens: invalid choice: 'factored'"),
    (("--maskgit_steps", "0"), "--maskgit_steps must be >= 1, got 0"),
    (("--temperature=-0.5",), "--temperature must be >= 0, got -0.5"),
])
def test_bad_decoding_flags_are_usage_errors(setup, tmp_path, capsys, extra, pattern):
    with pytest.raises(SystemExit) as exit_info:
        run(setup, tmp_path, *extra)
    assert exit_info.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]  # argparse's usage, then one error line
    assert line.startswith("generate.py: error: ") and re.search(pattern, line)
