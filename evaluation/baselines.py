"""Copy-the-last-frame baselines for the challenge metrics (docs/formats.md §5).

    python diagnose.py baselines --train_data_dir data/sample/train --val_data_dir data/sample/val

Token accuracy: predict frame t as a copy of ground-truth frame t-1. CE: the best smoothed copy, which puts
probability p on each factor of the previous frame's token and spreads 1-p uniformly over the other V-1 values;
the CE-optimal p is the factor match rate, fit on the training split and applied to the validation windows.

Previous-token lookup (a diagnostic of the accuracy metric): from the training pairs, predict the token that most
often followed the same token at the same position one window frame earlier (`lookup_acc`), or each factor's most
frequent value after it (`factored_lookup_acc`: what greedy sampling of factorized logits does when all a model
knows is that previous token); tokens never seen in training are copied. When the factor-wise choice scores
below copying, a factorized model needs more than the previous token at its position to beat the copy baseline.
"""
import math
from typing import Optional

import numpy as np
import torch

from common.errors import DataMismatchError
from data import RawTokenDataset
from genie.factorization import factorize_token_ids


def frame_pairs(dataset: RawTokenDataset, max_windows: int = None):
    """Yield (prev_BS, next_BS) int64 token pairs of consecutive window frames, one window at a time."""
    n = len(dataset) if max_windows is None else min(len(dataset), max_windows)
    s2 = dataset.metadata["s"] ** 2
    for i in range(n):
        x_TS = dataset[i]["tokens"].reshape(dataset.window_size, s2)
        yield x_TS[:-1], x_TS[1:]


def factor_match_rate(dataset: RawTokenDataset, num_factors: int, factor_size: int, max_windows: int = None) -> float:
    matches, total = 0, 0
    for prev, nxt in frame_pairs(dataset, max_windows):
        eq = factorize_token_ids(prev, num_factors, factor_size) == factorize_token_ids(nxt, num_factors, factor_size)
        matches += int(eq.sum())
        total += eq.numel()
    return matches / total


def copy_baseline(dataset: RawTokenDataset, p: float, num_factors: int, factor_size: int,
                  max_windows: int = None) -> dict:
    """Accuracy of copying frame t-1 and CE of the p-smoothed copy, averaged over every token of frames 1..T-1."""
    p = min(max(p, 1e-6), 1 - 1e-6)
    hit, miss = -math.log(p), -math.log((1 - p) / (factor_size - 1))
    acc_sum, ce_sum, n = 0.0, 0.0, 0
    for prev, nxt in frame_pairs(dataset, max_windows):
        acc_sum += float((prev == nxt).sum())
        eq = factorize_token_ids(prev, num_factors, factor_size) == factorize_token_ids(nxt, num_factors, factor_size)
        ce_sum += float(torch.where(eq, hit, miss).sum())
        n += prev.numel()
    return {"copy_acc": acc_sum / n, "smoothed_copy_loss": ce_sum / n, "p": p, "num_tokens": n}


def token_pairs(dataset: RawTokenDataset, max_windows: int = None):
    """All (prev, next) token ids of consecutive window frames at the same position: two (N,) int64 arrays."""
    pairs = [(prev.flatten(), nxt.flatten()) for prev, nxt in frame_pairs(dataset, max_windows)]
    if not pairs:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return (torch.cat([p for p, _ in pairs]).numpy().astype(np.int64),
            torch.cat([n for _, n in pairs]).numpy().astype(np.int64))


def most_frequent_successor(prev_N: np.ndarray, next_N: np.ndarray) -> dict:
    """{prev value: the next value seen most often after it} (ties: the smallest next value)."""
    if len(prev_N) == 0:
        return {}
    pairs_N2, counts = np.unique(np.stack([prev_N, next_N], 1), axis=0, return_counts=True)
    order = np.lexsort((pairs_N2[:, 1], -counts, pairs_N2[:, 0]))  # by prev, then count desc, then next asc
    pairs_N2 = pairs_N2[order]
    first = np.r_[True, pairs_N2[1:, 0] != pairs_N2[:-1, 0]]
    return dict(zip(pairs_N2[first, 0].tolist(), pairs_N2[first, 1].tolist()))


def lookup_baselines(train: RawTokenDataset, val: RawTokenDataset, num_factors: int, factor_size: int,
                     max_train_windows: int = None, max_windows: int = None) -> dict:
    """Accuracy of the previous-token lookup on val, joint and factor-wise (see the module docstring)."""
    prev_tr, next_tr = token_pairs(train, max_train_windows)
    prev_va, next_va = token_pairs(val, max_windows)
    joint = most_frequent_successor(prev_tr, next_tr)
    pred_joint = np.array([joint.get(t, t) for t in prev_va.tolist()], dtype=np.int64)
    pred_factored = np.zeros_like(prev_va)
    for k in range(num_factors):
        scale = factor_size ** k
        table = most_frequent_successor(prev_tr, next_tr // scale % factor_size)
        value = np.array([table.get(t, t // scale % factor_size) for t in prev_va.tolist()], dtype=np.int64)
        pred_factored += value * scale
    n = max(len(next_va), 1)
    return {"lookup_acc": float((pred_joint == next_va).sum() / n),
            "factored_lookup_acc": float((pred_factored == next_va).sum() / n)}


def factor_size_of(train: RawTokenDataset, val: RawTokenDataset, num_factored_vocabs: int) -> int:
    """The factored vocabulary size V of both splits (V ** F = vocab_size); errors name the split that differs."""
    vocab_size = val.vocab_size
    if train.vocab_size != vocab_size:
        raise DataMismatchError(f"{train.data_dir}: vocab_size {train.vocab_size} differs from {val.data_dir}'s "
                                f"{vocab_size}; the baselines need two splits of one tokenizer")
    factor_size = round(vocab_size ** (1 / num_factored_vocabs))
    if factor_size ** num_factored_vocabs != vocab_size:
        raise DataMismatchError(f"{val.data_dir}: vocab_size {vocab_size} is not a power of "
                                f"--num_factored_vocabs {num_factored_vocabs}; no factored vocabulary fits it")
    return factor_size


def baselines(train_data_dir, val_data_dir, window_size: int = 16, stride: int = 15, num_factored_vocabs: int = 2,
              max_train_windows: int = 2000, max_examples: Optional[int] = None) -> dict:
    """Every baseline of val_data_dir's windows (window_size frames at stride, non-overlapping; the first
    max_examples, default all), fitted on up to max_train_windows windows of train_data_dir: the JSON line of
    `diagnose.py baselines`."""
    train = RawTokenDataset(train_data_dir, window_size, stride, filter_overlaps=True)
    val = RawTokenDataset(val_data_dir, window_size, stride, filter_overlaps=True)
    factor_size = factor_size_of(train, val, num_factored_vocabs)
    p = factor_match_rate(train, num_factored_vocabs, factor_size, max_train_windows)
    result = copy_baseline(val, p, num_factored_vocabs, factor_size, max_examples)
    result.update(lookup_baselines(train, val, num_factored_vocabs, factor_size, max_train_windows, max_examples))
    result["num_examples"] = min(len(val), max_examples or len(val))
    return result
