"""python diagnose.py: per-window scores, withheld actions, one-line errors; and the decoding flags
(genie/decoding.py) that evaluate.py, generate.py and the diagnostics share. The copy ceiling's tests are in
tests/test_copy_ceiling.py, the breakdown's in tests/test_rollout_breakdown.py."""
import argparse
import json
import os

import numpy as np
import pytest
import torch

import evaluate
import play
import evaluation.protocols
from tests.cli_runner import run_as_main
import generate
from common.cli import run_main
from data import RawTokenDataset, write_token_dataset
from genie import STMaskGIT
from genie.decoding import GREEDY_TOKEN_CHOICES
from diagnose import build_parser, main
from evaluation.protocols import example_indices
from tests.test_evaluate import (REPO, VOCAB, error_line, eval_args, last_json_line, make_checkpoint,  # noqa: F401
                                 tiny)

K = 4  # latent actions of the action model
PER_HORIZON_KEYS = [f"{name}_{metric}" for name in ("rollout", "hold") for metric in ("psnr", "ssim")] + [
    f"{name}_{stat}" for name in ("rollout", "true") for stat in ("unchanged", "repeated")]


def diagnose(argv) -> int:
    return run_main("diagnose.py", main, argv)


def window_args(subcommand, data, *extra):
    return [subcommand, "--val_data_dir", str(data), "--window_size", "8", "--stride", "3", "--batch_size", "3",
            "--device", "cpu", *extra]


# ------------------------------------------------------------------ per_window (and copy_ceiling's --per_window_out)
@pytest.mark.parametrize("subcommand", ["per_window", "copy_ceiling"])
def test_per_window_scores_place_each_window_and_average_to_the_summary(tiny, tmp_path, capsys, subcommand):
    out = tmp_path / "not_yet" / "windows.jsonl"  # the parent directory is created
    model = ["--checkpoint_dir", str(tiny.ckpt)] if subcommand == "per_window" else []
    assert main(window_args(subcommand, tiny.data, *model, "--num_prompt_frames", "3", "--max_examples", "5",
                            "--spread_examples", "--tokenizer_ckpt", str(tiny.tokenizer), "--skip_lpips",
                            "--per_window_out", str(out))) == 0  # batches of 3: 3 + 2 windows
    summary = last_json_line(capsys.readouterr().out)
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    dataset = RawTokenDataset(tiny.data, window_size=8, stride=3, filter_overlaps=True)
    segment_ids = np.fromfile(tiny.data / "segment_ids.bin", dtype="<i4")
    assert [line["window"] for line in lines] == example_indices(len(dataset), 5, True)
    for line in lines:
        assert line["first_frame"] == dataset.valid_start_inds[line["window"]]
        assert line["segment_id"] == segment_ids[line["first_frame"]]
        assert "rollout_lpips" not in line  # --skip_lpips
    for key in PER_HORIZON_KEYS:
        assert all(len(line[key]) == 8 - 3 for line in lines)
        assert np.mean([line[key] for line in lines], axis=0) == pytest.approx(summary[key], abs=1e-5)
    assert len({tuple(line["hold_psnr"]) for line in lines}) == 5  # each window's own scores, not the mean

    if subcommand == "per_window":  # the summary is evaluate.py's rollout line for the same flags
        assert evaluate.main(eval_args(tiny.data, tiny.ckpt, "--protocol", "rollout", "--num_prompt_frames", "3",
                                       "--max_examples", "5", "--spread_examples", "--tokenizer_ckpt",
                                       str(tiny.tokenizer), "--skip_lpips")) == 0
        rollout = last_json_line(capsys.readouterr().out)
        assert set(rollout) == set(summary)
        assert {k: v for k, v in rollout.items() if k != "gen_time"} == \
            {k: v for k, v in summary.items() if k != "gen_time"}


@pytest.mark.parametrize("extra, message", [
    ([], "the following arguments are required: --per_window_out"),
    (["--per_window_out", ".", "--num_prompt_frames", "3"], "is a directory"),
    (["--per_window_out", "w.jsonl", "--num_prompt_frames", "8"], "--num_prompt_frames must be in 1..7"),
    (["--per_window_out", "w.jsonl", "--stall_ratio", "0.5", "--num_prompt_frames", "1"],
     "needs --num_prompt_frames >= 2, got 1"),
    (["--per_window_out", "w.jsonl", "--greedy_tokens", "factored"], "invalid choice: 'factored'"),
])
def test_bad_per_window_flags_are_usage_errors(tiny, capsys, extra, message):
    with pytest.raises(SystemExit) as exit_info:
        main(window_args("per_window", tiny.data, "--checkpoint_dir", str(tiny.ckpt), *extra))
    assert exit_info.value.code == 2
    line = error_line(capsys.readouterr().err)
    assert line.startswith("diagnose.py per_window: error: ") and message in line


# ------------------------------------------------------------------ withheld_actions
@pytest.fixture(scope="module")
def action_world(tmp_path_factory):
    """A latent-action checkpoint (K ids), a dataset with actions/latent_action.bin and one without actions/."""
    root = tmp_path_factory.mktemp("withheld")
    rng = np.random.default_rng(3)
    video = rng.integers(0, VOCAB, size=(60, 4, 4))
    segment_ids = np.repeat(np.arange(2), 30)
    latent = rng.integers(0, K, size=(60, 1)).astype(np.float32)
    write_token_dataset(root / "with_actions", video, segment_ids=segment_ids, actions={"latent_action": latent},
                        metadata={"vocab_size": VOCAB})
    write_token_dataset(root / "plain", video, segment_ids=segment_ids, metadata={"vocab_size": VOCAB})
    model = STMaskGIT.from_pretrained(make_checkpoint(root / "base", num_latent_actions=K))
    with torch.no_grad():  # visible latent actions, and a copy of the model for which every id is "no action"
        model.action_cond.latent_action_embed.weight.normal_(0, 1.0)
        model.save_pretrained(root / "ckpt")
        table = model.action_cond.latent_action_embed.weight
        table.copy_(table[K].expand_as(table))
    model.save_pretrained(root / "blind")
    return root


def withheld_args(world, data, *extra):
    return ["withheld_actions", "--checkpoint_dir", str(world / "ckpt"), "--val_data_dir", str(world / data),
            "--window_size", "8", "--stride", "1", "--max_examples", "3", "--device", "cpu", "--skip_lpips", *extra]


def test_withheld_actions_gives_the_model_none(action_world, tiny, tmp_path, capsys, monkeypatch):
    calls = []
    for name in ("generate_frames", "teacher_forced"):
        real = getattr(evaluation.protocols, name)
        monkeypatch.setattr(evaluation.protocols, name,
                            lambda *a, real=real, **kw: calls.append(kw) or real(*a, **kw))
    # the rollout protocol on a dataset without actions/: no action stream needed
    out = tmp_path / "windows.jsonl"
    assert main(withheld_args(action_world, "plain", "--protocol", "rollout", "--num_prompt_frames", "2",
                              "--tokenizer_ckpt", str(tiny.tokenizer),
                              "--per_window_out", str(out))) == 0
    result = last_json_line(capsys.readouterr().out)
    assert result["actions_withheld"] is True and result["protocol"] == "rollout"
    assert len(result["rollout_psnr"]) == 6 and len(out.read_text().splitlines()) == 3
    assert calls and all(kw["actions"] is None and kw["latent_actions"] is None for kw in calls)

    # teacher-forced: what a model whose every latent id embeds like "no action" scores, no latent-action metrics
    calls.clear()
    assert main(withheld_args(action_world, "with_actions")) == 0
    withheld = last_json_line(capsys.readouterr().out)
    assert calls and all(kw["latent_actions"] is None for kw in calls)
    assert withheld["actions_withheld"] is True and "delta_psnr" not in withheld
    assert set(withheld) == set(evaluation.protocols.TEACHER_FORCED_KEYS) | {"num_examples", "actions_withheld",
                                                                            "decoding"}
    blind_argv = ["--checkpoint_dir", str(action_world / "blind"), "--val_data_dir", str(action_world / "with_actions"),
                  "--window_size", "8", "--stride", "1", "--max_examples", "3", "--device", "cpu", "--skip_lpips",
                  "--train_data_dir", str(tmp_path / "none")]  # no latent action probe
    assert evaluate.main(blind_argv) == 0
    blind = last_json_line(capsys.readouterr().out)
    assert blind["loss"] == pytest.approx(withheld["loss"], rel=1e-6) and blind["acc"] == withheld["acc"]
    assert evaluate.main(blind_argv[:1] + [str(action_world / "ckpt")] + blind_argv[2:]) == 0
    assert last_json_line(capsys.readouterr().out)["loss"] != withheld["loss"]  # the actions matter


def test_withheld_actions_needs_a_model_with_actions(tiny, capsys):
    assert diagnose(["withheld_actions", "--checkpoint_dir", str(tiny.ckpt), "--val_data_dir", str(tiny.data),
                     "--window_size", "8", "--stride", "3", "--device", "cpu", "--skip_lpips"]) == 1
    line = error_line(capsys.readouterr().err)
    assert line.startswith("diagnose.py: error: withheld_actions: the checkpoint") and "takes no actions" in line


@pytest.mark.parametrize("extra, message", [
    (["--per_window_out", "w.jsonl"], "--per_window_out applies to --protocol rollout only"),
    (["--num_prompt_frames", "3"], "--num_prompt_frames applies to --protocol rollout only"),
    (["--protocol", "rollout", "--num_prompt_frames", "3", "--save_outputs_dir", "out"],
     "does not apply to --protocol rollout"),
    (["--delta_psnr_seeds", "2"], "unrecognized arguments: --delta_psnr_seeds"),
])
def test_bad_withheld_actions_flags_are_usage_errors(action_world, capsys, extra, message):
    with pytest.raises(SystemExit) as exit_info:
        main(withheld_args(action_world, "plain", *extra))
    assert exit_info.value.code == 2
    assert message in error_line(capsys.readouterr().err)


# ------------------------------------------------------------------ the command line
def test_bad_input_ends_the_command_in_one_line(tiny, tmp_path):
    """As `python diagnose.py`: a usage error (exit status 2) and a missing dataset (1) end in one error
    line, no traceback."""
    env = {k: v for k, v in os.environ.items() if k != "WORLD_SIZE"}
    cases = [(["breakdown", "windows.jsonl"], 2,
              "diagnose.py breakdown: error: the following arguments are required: --val_data_dir"),
             (["copy_ceiling", "--val_data_dir", str(tmp_path / "missing"), "--skip_lpips"], 1,
              f"diagnose.py: error: {tmp_path / 'missing'}"),
             ([], 2, "diagnose.py: error: the following arguments are required: SUBCOMMAND")]
    ran = run_as_main({i: ("diagnose.py", argv) for i, (argv, _, _) in enumerate(cases)}, env=env)
    for i, (argv, code, message) in enumerate(cases):
        proc = ran[i]
        assert proc.returncode == code and proc.stdout == ""
        assert error_line(proc.stderr).startswith(message), proc.stderr


def subcommand_parsers():
    parser = build_parser()
    (subparsers,) = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    return subparsers.choices


def command_parsers():
    """(name, parser) of every command line: evaluate.py, generate.py, play.py, each diagnostic."""
    parsers = {"evaluate.py": evaluate_parser(), "generate.py": generate_parser(), "play.py": capture_parser(play, [])}
    parsers.update({f"diagnostics {name}": sub for name, sub in subcommand_parsers().items()})
    return parsers


def capture_parser(module, argv):
    """The ArgumentParser that module.parse_args builds (caught as it parses argv)."""
    seen = []
    real = argparse.ArgumentParser.parse_args

    def spy(self, args=None, namespace=None):
        seen.append(self)
        return real(self, args, namespace)

    argparse.ArgumentParser.parse_args = spy
    try:
        module.parse_args(argv)
    finally:
        argparse.ArgumentParser.parse_args = real
    return seen[0]


def evaluate_parser():
    return capture_parser(evaluate, [])


def generate_parser():
    return capture_parser(generate, [])


def test_every_flag_is_explained_in_help():
    for name, parser in command_parsers().items():
        for action in parser._actions:
            assert action.help and len(action.help) > 10, (name, action.option_strings)
        parser.format_help()  # every %(default)s expands


def test_the_decoding_flags_are_one_definition():
    """The same decoding flags, choices and help in every command that samples frames, each unset by default (the
    checkpoint's decoding.json decides); --greedy_tokens offers exactly the model's choices."""
    decoding = ("--maskgit_steps", "--temperature", "--unmask_mode", "--copy_bias", "--greedy_tokens", "--stall_ratio")
    seen = {}
    for name, parser in command_parsers().items():
        flags = {option: action for action in parser._actions for option in action.option_strings}
        if name in ("diagnostics copy_ceiling", "diagnostics breakdown", "diagnostics baselines"):  # no model decodes
            assert not set(decoding) & set(flags), name
            continue
        described = {flag: (flags[flag].default, flags[flag].choices, flags[flag].help) for flag in decoding}
        assert all(default is None for default, _, _ in described.values()), name
        seen.setdefault("first", described)
        assert described == seen["first"], name
    assert seen["first"]["--greedy_tokens"][1] == tuple(GREEDY_TOKEN_CHOICES) == ("joint", "best_neighbour")


def test_help_of_every_command(capsys):
    for argv in ([], ["copy_ceiling"], ["per_window"], ["breakdown"], ["withheld_actions"], ["control"],
                 ["baselines"]):
        with pytest.raises(SystemExit) as exit_info:
            main([*argv, "--help"])
        assert exit_info.value.code == 0
        out = capsys.readouterr().out
        assert out.startswith(f"usage: diagnose.py {' '.join(argv)}".rstrip())
