"""common/cli.py: the shared --device / --num_threads flags, hidden aliases of renamed flags, one log format."""
import argparse
import importlib

import pytest
import torch

from common.cli import add_device_arg, add_hidden_alias, cpu_has_native_bf16, resolve_device, run_main
from sample_world import build as build_sample
from magvit2 import train as magvit2_train


def test_resolve_device():
    assert resolve_device("auto") == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="unknown device 'gpu'"):
        resolve_device("gpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="CUDA is not available"):
            resolve_device("cuda:0")


def test_device_flag_defaults_to_auto_and_rejects_unknown_devices(capsys):
    parser = argparse.ArgumentParser()
    add_device_arg(parser)
    assert parser.parse_args([]).device == "auto"
    assert parser.parse_args(["--device", "cpu"]).device == "cpu"
    with pytest.raises(SystemExit):
        parser.parse_args(["--device", "gpu"])
    assert "argument --device: unknown device 'gpu'" in capsys.readouterr().err


def test_hidden_alias_sets_the_same_option_and_stays_out_of_help():
    parser = argparse.ArgumentParser()
    parser.add_argument("--adam_beta_1", type=float, default=0.5)
    add_hidden_alias(parser, "--adam_beta1", "adam_beta_1", type=float)
    assert parser.parse_args([]).adam_beta_1 == 0.5
    assert parser.parse_args(["--adam_beta1", "0.7"]).adam_beta_1 == 0.7
    assert "adam_beta1" not in parser.format_help()


def test_renamed_flags_keep_their_old_spelling():
    old = magvit2_train.parse_args(["--train_data", "x.npz", "--output_dir", "o", "--adam_beta1", "0.8",
                                    "--adam_beta2", "0.95"])
    assert (old.adam_beta_1, old.adam_beta_2) == (0.8, 0.95)
    new = magvit2_train.parse_args(["--train_data", "x.npz", "--output_dir", "o"])
    assert (new.adam_beta_1, new.adam_beta_2) == (0.5, 0.9)
    args = build_sample.parse_args(["--out_dir", "somewhere", "--tokenizer", "tok"])
    assert (args.output_dir, args.tokenizer_ckpt) == ("somewhere", "tok")


def test_build_sample_passes_the_training_walks_length_through(monkeypatch, capsys):
    seen = {}

    class Stop(Exception):
        pass

    def fake_build(raw, **kwargs):
        seen.update(kwargs)
        raise Stop

    monkeypatch.setattr(build_sample, "build_sample_world", fake_build)
    with pytest.raises(Stop):
        build_sample.main(["--output_dir", "somewhere", "--train_episode_len", "1000"])
    assert (seen["train_episode_len"], seen["episode_len"]) == (1000, 1500)
    with pytest.raises(Stop):
        build_sample.main(["--output_dir", "somewhere"])
    assert seen["train_episode_len"] is None
    with pytest.raises(SystemExit):
        build_sample.parse_args(["--train_episode_len", "0"])
    assert "--train_episode_len must be >= 1" in capsys.readouterr().err


@pytest.mark.parametrize("text, expected", [
    ("processor\t: 0\nflags\t\t: fpu sse2 avx512f avx512_bf16 avx512_vnni\n", True),     # AVX512-BF16
    ("processor\t: 0\nflags\t\t: fpu sse2 avx512f amx_tile amx_bf16\n", True),          # AMX
    ("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw avx512_vnni\n", False),  # AVX-512 without bf16
    ("processor\t: 0\nFeatures\t: fp asimd sve bf16 i8mm\n", True),                      # Arm with FEAT_BF16
    ("processor\t: 0\nFeatures\t: fp asimd evtstrm crc32\n", False),
    ("processor\t: 0\nmodel name\t: some CPU\n", None),                                  # no flag line
])
def test_cpu_has_native_bf16_reads_the_feature_flags(tmp_path, text, expected):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text(text)
    assert cpu_has_native_bf16(str(cpuinfo)) is expected


def test_cpu_has_native_bf16_is_unknown_without_cpuinfo(tmp_path):
    assert cpu_has_native_bf16(str(tmp_path / "missing")) is None


# every script that trains, evaluates, generates, tokenizes or decodes, with the least argv its parser accepts
THREADED_SCRIPTS = [
    ("train", []),
    ("evaluate", []),
    ("generate", []),
    ("visualize", ["--token_dir", "tokens"]),
    ("magvit2.tokenize_frames", ["frames.npz", "--tokenizer_ckpt", "tok", "--output_dir", "out"]),
    ("sample_world.build", []),
    ("magvit2.train", ["--train_data", "x.npz", "--output_dir", "o"]),
    ("lam.train", ["--train_data", "x.npz", "--output_dir", "o"]),
    ("lam.label", ["--lam_dir", "lam", "--frames", "x.npz", "--token_dir", "tokens"]),
]


@pytest.mark.parametrize("module, argv", THREADED_SCRIPTS, ids=[m for m, _ in THREADED_SCRIPTS])
def test_every_torch_script_takes_num_threads(module, argv, capsys):
    parse_args = importlib.import_module(module).parse_args
    assert parse_args(argv).num_threads == 0  # torch's own default
    assert parse_args([*argv, "--num_threads", "1"]).num_threads == 1
    with pytest.raises(SystemExit):
        parse_args([*argv, "--num_threads", "-2"])
    assert "argument --num_threads: must be 0 or more, got -2" in capsys.readouterr().err


@pytest.mark.parametrize("module, argv", [s for s in THREADED_SCRIPTS if s[0] != "sample_world.build"],
                         ids=[m for m, _ in THREADED_SCRIPTS if m != "sample_world.build"])
def test_every_torch_script_applies_num_threads_before_its_inputs(module, argv, tmp_path, monkeypatch):
    """The count is set before anything is read: here every input is missing, so the script stops with its error
    (build_sample is left out: with nothing built yet it would start rendering)."""
    calls = []
    monkeypatch.setattr(torch, "set_num_threads", calls.append)
    monkeypatch.chdir(tmp_path)  # the relative inputs above and the scripts' defaults do not exist here
    try:
        code = run_main(module, importlib.import_module(module).main, [*argv, "--num_threads", "3"])
    except SystemExit as stop:  # train.py ends in its own one-line exit
        code = stop.code
    assert code not in (0, None)
    assert calls == [3]


@pytest.mark.parametrize("module, argv, flag", [
    ("train", [], "--learning_rate"), ("train", [], "--weight_decay"), ("evaluate", [], "--temperature"),
    ("generate", [], "--copy_bias"), ("lam.train", ["--train_data", "x.npz"], "--max_grad_norm"),
    ("magvit2.train", ["--train_data", "x.npz", "--output_dir", "o"], "--learning_rate"),
])
@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_float_flags_reject_nan_and_inf(module, argv, flag, value, capsys):
    """nan or inf would surface as a traceback from deep inside torch (an optimizer's "Invalid learning rate",
    a sampler's "probability tensor contains nan"), or as meaningless numbers."""
    with pytest.raises(SystemExit):
        importlib.import_module(module).parse_args([*argv, f"{flag}={value}"])  # "=": "-inf" is not an option
    assert f"argument {flag}: must be a finite number, got {value}" in capsys.readouterr().err


@pytest.mark.parametrize("module, argv, flags, message", [
    ("train", [], ["--learning_rate", "0"], "--learning_rate must be > 0, got 0.0"),
    ("train", [], ["--adam_eps=-1e-8"], "--adam_eps must be > 0, got -1e-08"),
    ("train", [], ["--weight_decay=-0.1"], "--weight_decay must be >= 0, got -0.1"),
    ("train", [], ["--adam_beta_2", "1"], "--adam_beta_2 must be in [0, 1), got 1.0"),
    ("train", [], ["--muon_momentum=-0.5"], "--muon_momentum must be in [0, 1), got -0.5"),
    ("lam.train", [], ["--learning_rate=-1"], "--learning_rate must be > 0, got -1.0"),
    ("magvit2.train", ["--train_data", "x.npz", "--output_dir", "o"], ["--disc_learning_rate", "0"],
     "--disc_learning_rate must be > 0, got 0.0"),
    ("magvit2.train", ["--train_data", "x.npz", "--output_dir", "o"], ["--adam_beta_1", "1.5"],
     "--adam_beta_1 must be in [0, 1), got 1.5"),
])
def test_training_scripts_reject_optimizer_settings_out_of_range(module, argv, flags, message, capsys):
    """Caught by the parser with the flag's name, not by the optimizer with a traceback."""
    with pytest.raises(SystemExit):
        importlib.import_module(module).parse_args([*argv, *flags])
    assert message in capsys.readouterr().err


def test_count_and_directory_flag_types_refuse_bad_values_in_one_usage_line(tmp_path, capsys):
    from common.cli import existing_dir, positive_float, positive_int

    parser = argparse.ArgumentParser(prog="prog")
    parser.add_argument("--steps", type=positive_int)
    parser.add_argument("--fps", type=positive_float)
    parser.add_argument("--dir", type=existing_dir)
    args = parser.parse_args(["--steps", "3", "--fps", "2.5", "--dir", str(tmp_path)])
    assert (args.steps, args.fps, args.dir) == (3, 2.5, tmp_path)
    (tmp_path / "file").write_text("")
    for flags, message in [(["--steps", "0"], "argument --steps: must be 1 or more, got 0"),
                           (["--steps", "2.5"], "argument --steps: expected an integer, got '2.5'"),
                           (["--fps", "0"], "argument --fps: must be > 0, got 0"),
                           (["--fps", "nan"], "argument --fps: must be a finite number, got nan"),
                           (["--dir", str(tmp_path / "missing")], "missing: no such directory"),
                           (["--dir", str(tmp_path / "file")], "file: not a directory")]:
        with pytest.raises(SystemExit):
            parser.parse_args(flags)
        line = capsys.readouterr().err.strip().splitlines()[-1]
        assert line.startswith("prog: error: ") and message in line


def test_run_main_ends_on_a_path_in_the_way_in_one_line_and_lets_bugs_through(capsys):
    from common.cli import run_main

    def in_the_way(argv):
        raise FileExistsError("out: already exists\n(pass --overwrite)")

    assert run_main("prog", in_the_way, []) == 1
    assert capsys.readouterr().err == "prog: error: out: already exists (pass --overwrite)\n"

    def bug(argv):
        raise ZeroDivisionError("a bug keeps its traceback")

    with pytest.raises(ZeroDivisionError):
        run_main("prog", bug, [])
