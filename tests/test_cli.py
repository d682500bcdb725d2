"""common/cli.py: the shared --device / --num_threads flags, hidden aliases of renamed flags, one log format."""
import argparse

import pytest
import torch

from common.cli import add_device_arg, add_hidden_alias, resolve_device
from magvit2 import build_sample
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
