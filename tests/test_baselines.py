"""Copy-the-last-frame baselines against hand-computed values on a tiny dataset."""
import json
import math
import re

import numpy as np
import pytest

from common.cli import run_main
from data import RawTokenDataset, write_token_dataset
from diagnose import main
from evaluation.baselines import copy_baseline, factor_match_rate, lookup_baselines


def _dataset(path, frames_NHW):
    write_token_dataset(path, frames_NHW, metadata={"vocab_size": 16, "hz": 35})
    return RawTokenDataset(path, window_size=3, stride=1, filter_overlaps=True)


def test_copy_baseline_matches_hand_computation(tmp_path):
    # 3 frames of 2x2 tokens, vocab 16 = 4 x 4 factors (t = f0 + 4 f1).
    f0 = np.array([[0, 1], [2, 3]])
    f1 = np.array([[0, 1], [2, 7]])    # last token: 3 -> 7 changes factor 1 only
    f2 = np.array([[5, 1], [2, 7]])    # first token: 0 -> 5 changes both factors
    ds = _dataset(tmp_path / "d", np.stack([f0, f1, f2]))
    # pairs (f0 -> f1): 3 of 4 tokens equal; factor matches 7 of 8. (f1 -> f2): 3 of 4; factors 6 of 8.
    p = factor_match_rate(ds, 2, 4)
    assert math.isclose(p, 13 / 16)
    res = copy_baseline(ds, 0.5, 2, 4)
    assert math.isclose(res["copy_acc"], 6 / 8)
    hit, miss = -math.log(0.5), -math.log(0.5 / 3)
    expected = (13 * hit + 3 * miss) / 8  # 16 factor terms summed over 8 tokens
    assert math.isclose(res["smoothed_copy_loss"], expected, rel_tol=1e-6)


def test_fitted_p_minimises_ce(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 16, size=(40, 2, 2))
    frames[1::2] = frames[::2]  # every other frame is a copy: a strong copy signal
    ds = _dataset(tmp_path / "d", frames)
    p = factor_match_rate(ds, 2, 4)
    best = copy_baseline(ds, p, 2, 4)["smoothed_copy_loss"]
    for other in (p * 0.8, min(0.99, p * 1.1)):
        assert copy_baseline(ds, other, 2, 4)["smoothed_copy_loss"] > best


def test_cli_prints_json(tmp_path, capsys):
    frames = np.random.default_rng(1).integers(0, 16, size=(12, 2, 2))
    _dataset(tmp_path / "t", frames)
    _dataset(tmp_path / "v", frames[::-1].copy())
    main(["baselines", "--train_data_dir", str(tmp_path / "t"), "--val_data_dir", str(tmp_path / "v"), "--window_size", "3",
          "--stride", "1"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(out) >= {"copy_acc", "smoothed_copy_loss", "p", "num_examples", "lookup_acc", "factored_lookup_acc"}
    assert 0 <= out["copy_acc"] <= 1


def test_lookup_baselines_pick_joint_and_factorwise_successors(tmp_path):
    # Windows of 2 frames of one token (vocab 16 = 4 x 4, t = f0 + 4 f1); each window is one (prev -> next) pair.
    # After token 0 came 0, 0, 5, 9, 13: the joint lookup predicts 0 (2 of 5), but factor by factor the most
    # frequent values are f0 = 1 (5, 9, 13) and f1 = 0 (0, 0), i.e. token 1, which never followed 0.
    # Token 3 was followed by 7 once. Unseen tokens are copied.
    train_pairs = [(0, 0), (0, 0), (0, 5), (0, 9), (0, 13), (3, 7)]
    val_pairs = [(0, 0), (0, 1), (3, 7), (3, 3), (8, 8), (8, 2)]

    def windows(pairs):
        return np.array(pairs).reshape(-1, 1, 1)

    train = RawTokenDataset(_write(tmp_path / "t", windows(train_pairs)), window_size=2, stride=1,
                            filter_overlaps=True)
    val = RawTokenDataset(_write(tmp_path / "v", windows(val_pairs)), window_size=2, stride=1, filter_overlaps=True)
    res = lookup_baselines(train, val, 2, 4)
    # joint predictions 0, 0, 7, 7, 8, 8: right on (0,0), (3,7), (8,8);
    # factor-wise predictions 1, 1, 7, 7, 8, 8: right on (0,1), (3,7), (8,8)
    assert math.isclose(res["lookup_acc"], 3 / 6)
    assert math.isclose(res["factored_lookup_acc"], 3 / 6)
    val2 = RawTokenDataset(_write(tmp_path / "v2", windows([(0, 0), (0, 0), (0, 1)])), window_size=2, stride=1,
                           filter_overlaps=True)
    res2 = lookup_baselines(train, val2, 2, 4)
    assert math.isclose(res2["lookup_acc"], 2 / 3) and math.isclose(res2["factored_lookup_acc"], 1 / 3)


def _write(path, frames_NHW):
    write_token_dataset(path, frames_NHW, metadata={"vocab_size": 16, "hz": 35})
    return path


def test_cli_names_the_bad_input_in_one_line(tmp_path, capsys):
    frames = np.random.default_rng(1).integers(0, 16, size=(12, 2, 2))
    _dataset(tmp_path / "t", frames)
    args = ["--window_size", "3", "--stride", "1"]

    def error(argv):  # stderr's one line of the command, exit status 1
        capsys.readouterr()
        assert run_main("diagnose.py", main, ["baselines", *argv]) == 1
        return capsys.readouterr().err.splitlines()[-1]

    missing = ["--train_data_dir", str(tmp_path / "t"), "--val_data_dir", str(tmp_path / "missing"), *args]
    assert re.match("^diagnose.py: error: .*missing: token dataset directory not found", error(missing))
    write_token_dataset(tmp_path / "v64", frames, metadata={"vocab_size": 64, "hz": 35})
    assert re.search("t: vocab_size 16 differs from .*v64's 64",
                     error(["--train_data_dir", str(tmp_path / "t"), "--val_data_dir", str(tmp_path / "v64"), *args]))
    write_token_dataset(tmp_path / "t12", frames % 12, metadata={"vocab_size": 12, "hz": 35})
    assert re.search("t12: vocab_size 12 is not a power of --num_factored_vocabs 2",
                     error(["--train_data_dir", str(tmp_path / "t12"), "--val_data_dir", str(tmp_path / "t12"), *args]))
    with pytest.raises(SystemExit):
        main(["baselines", "--train_data_dir", str(tmp_path / "t"), "--val_data_dir", str(tmp_path / "t"), "--max_examples", "0"])
