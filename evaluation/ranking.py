"""How well one scoring of policies ranks them against the truth: rank correlations, pairwise accuracy, regret@1,
Pearson r and SIMPLER's mean maximum rank violation, and how sure each figure is (a bootstrap interval over the
starts, a permutation p-value).

Every metric takes the true returns and the predicted returns of the same policies, in the same order (1-D
sequences of equal length >= 2). Ties count as in the usual definitions: average ranks for Spearman, tau-b for
Kendall, half a point for a pair tied in the prediction only.
"""
import itertools
from typing import Callable, Sequence, Tuple

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
    return pearson(average_ranks(t), average_ranks(p))


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


def pearson(truth, predicted) -> float:
    """Pearson r of the returns themselves; 0 when either side is constant."""
    t, p = _pair(truth, predicted)
    t, p = t - t.mean(), p - p.mean()
    denominator = np.sqrt((t ** 2).sum() * (p ** 2).sum())
    return float((t * p).sum() / denominator) if denominator > 0 else 0.0


def mean_maximum_rank_violation(truth, predicted) -> float:
    """SIMPLER's MMRV (Li et al. 2024), in the truth's units: for each policy i, the largest true gap |t_i - t_j|
    over the policies j that the prediction orders the other way than the truth (orders by strict >, so a pair tied
    on one side only counts as reversed), averaged over i. 0 for a ranking that agrees on every pair."""
    t, p = _pair(truth, predicted)
    reversed_NN = (p[:, None] > p[None, :]) != (t[:, None] > t[None, :])
    gaps_NN = np.abs(t[:, None] - t[None, :])
    return float(np.where(reversed_NN, gaps_NN, 0.0).max(axis=1).mean())


def bootstrap_interval(statistic: Callable[..., float], *returns_SN, num_resamples: int = 2000, level: float = 0.95,
                       seed: int = 0) -> Tuple[float, float]:
    """Percentile interval of statistic(*mean returns) over the starts: each of returns_SN holds per-start returns
    (S starts, N policies); each resample draws S starts with replacement, the same starts for every array and
    policy, and passes the policies' mean returns (N,) over them to `statistic`."""
    arrays = [np.asarray(r, dtype=np.float64) for r in returns_SN]
    if not arrays or any(a.ndim != 2 or a.shape != arrays[0].shape or len(a) < 1 for a in arrays):
        raise ValueError(f"need per-start returns (starts, policies) of one shape, got {[a.shape for a in arrays]}")
    rng = np.random.default_rng(seed)
    S = len(arrays[0])
    values = []
    for _ in range(num_resamples):
        rows = rng.integers(0, S, S)
        values.append(statistic(*(a[rows].mean(0) for a in arrays)))
    low, high = np.quantile(values, [(1 - level) / 2, (1 + level) / 2])
    return float(low), float(high)


def spearman_p_value(truth, predicted, max_exact: int = 9, num_permutations: int = 100000, seed: int = 0) -> float:
    """One-sided permutation p-value of Spearman's rho against a prediction unrelated to the truth: the share of
    orderings of the predicted returns whose rho is at least the observed one. Every ordering for up to max_exact
    policies (9! = 362,880), else num_permutations random ones (the observed ordering counted once more, so p > 0)."""
    t, p = _pair(truth, predicted)
    rt, rp = average_ranks(t), average_ranks(p)
    rt = rt - rt.mean()
    # rho of a reordering is (rt . rp[order]) / const, so comparing the dot products is enough
    observed = float(rt @ rp) - 1e-9
    n = len(p)
    if n <= max_exact:
        orders_KN = np.array(list(itertools.permutations(range(n))))
        return float((rp[orders_KN] @ rt >= observed).mean())
    rng = np.random.default_rng(seed)
    orders_KN = np.argsort(rng.random((num_permutations, n)), axis=1)
    return float(((rp[orders_KN] @ rt >= observed).sum() + 1) / (num_permutations + 1))
