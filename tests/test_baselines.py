"""Copy-the-last-frame baselines against hand-computed values on a tiny dataset."""
import json
import math

import numpy as np

from data import RawTokenDataset, write_token_dataset
from genie.baselines import copy_baseline, factor_match_rate, main


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
    main(["--train_data_dir", str(tmp_path / "t"), "--val_data_dir", str(tmp_path / "v"), "--window_size", "3",
          "--stride", "1"])
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert set(out) >= {"copy_acc", "smoothed_copy_loss", "p", "num_examples"}
    assert 0 <= out["copy_acc"] <= 1
