"""How well one scoring of policies ranks them against the truth: rank correlations, pairwise accuracy, regret@1.

Every function takes the true returns and the predicted returns of the same policies, in the same order (1-D
sequences of equal length >= 2). Ties count as in the usual definitions: average ranks for Spearman, tau-b for
Kendall, half a point for a pair tied in the prediction only.
"""
from typing import Sequence

import numpy as np


def _pair(truth: Sequence[float], predicted: Sequence[float]):
    t, p = np.asarray(truth, dtype=np.float64), np.asarray(predicted, dtype=np.float64)
    if t.ndim != 1 or t.shape != p.shape or len(t) < 2:
        raise ValueError(f"need two 1-D sequences of the same length >= 2, got shapes {t.shape} and {p.shape}")
    if not (np.isfinite(t).all() and np.isfinite(p).all()):
        raise ValueError("returns must be finite")
    return t, p


def average_ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n, ties sharing the mean of their ranks."""
    order = np.argsort(values, kind="stable")
    ranks = np.empty(len(values))
    sorted_values = values[order]
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and sorted_values[j + 1] == sorted_values[i]:
            j += 1
        ranks[order[i:j + 1]] = (i + j) / 2 + 1
        i = j + 1
    return ranks


def spearman(truth, predicted) -> float:
    """Pearson correlation of the average ranks; 0 when either side is constant."""
    t, p = _pair(truth, predicted)
    rt, rp = average_ranks(t), average_ranks(p)
    rt, rp = rt - rt.mean(), rp - rp.mean()
    denominator = np.sqrt((rt ** 2).sum() * (rp ** 2).sum())
    return float((rt * rp).sum() / denominator) if denominator > 0 else 0.0


def _pair_signs(t: np.ndarray, p: np.ndarray):
    i, j = np.triu_indices(len(t), k=1)
    return np.sign(t[i] - t[j]), np.sign(p[i] - p[j])


def kendall(truth, predicted) -> float:
    """Kendall's tau-b; 0 when either side is constant."""
    st, sp = _pair_signs(*_pair(truth, predicted))
    denominator = np.sqrt((st != 0).sum() * (sp != 0).sum())
    return float((st * sp).sum() / denominator) if denominator > 0 else 0.0


def pairwise_accuracy(truth, predicted) -> float:
    """Share of the pairs the truth orders (ties in the truth skipped) that the prediction orders the same way; a
    pair the prediction ties counts one half."""
    st, sp = _pair_signs(*_pair(truth, predicted))
    ordered = st != 0
    if not ordered.any():
        return 1.0
    agree = np.where(sp[ordered] == 0, 0.5, (st[ordered] == sp[ordered]).astype(np.float64))
    return float(agree.mean())


def regret_at_1(truth, predicted) -> float:
    """The best true return minus the true return of the prediction's top pick (ties in the prediction: their mean
    true return)."""
    t, p = _pair(truth, predicted)
    top = p == p.max()
    return float(t.max() - t[top].mean())
