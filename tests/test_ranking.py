"""evaluation/ranking.py against values computed by hand (and scipy's definitions, where they agree)."""
import numpy as np
import pytest

from evaluation.ranking import (average_ranks, bootstrap_interval, kendall, mean_maximum_rank_violation,
                                pairwise_accuracy, pearson, regret_at_1, spearman, spearman_p_value)


def test_perfect_reversed_and_hand_computed_rankings():
    truth = [1.0, 2.0, 3.0, 4.0]
    assert spearman(truth, [10, 20, 30, 40]) == pytest.approx(1.0)
    assert spearman(truth, [4, 3, 2, 1]) == pytest.approx(-1.0)
    # one adjacent swap of four: d = (0, 0, 1, -1), rho = 1 - 6 * 2 / (4 * 15) = 0.8; 5 of 6 pairs agree
    assert spearman(truth, [1, 2, 4, 3]) == pytest.approx(0.8)
    assert kendall(truth, [1, 2, 4, 3]) == pytest.approx((5 - 1) / 6)
    assert pairwise_accuracy(truth, [1, 2, 4, 3]) == pytest.approx(5 / 6)
    assert regret_at_1(truth, [1, 2, 4, 3]) == pytest.approx(1.0)  # picks the second best: 4 - 3
    assert regret_at_1(truth, [0, 0, 0, 9]) == 0.0


def test_ties():
    np.testing.assert_allclose(average_ranks(np.array([5.0, 1.0, 5.0, 3.0])), [3.5, 1, 3.5, 2])
    # the prediction ties the top two: half a point for that pair, regret the mean of the tied picks' truth
    assert pairwise_accuracy([1, 2, 3], [1, 5, 5]) == pytest.approx((1 + 1 + 0.5) / 3)
    assert regret_at_1([1, 2, 3], [1, 5, 5]) == pytest.approx(3 - 2.5)
    # tau-b with a tie in the prediction: concordant 2, discordant 0, n0 = 3, ties in p 1 -> 2 / sqrt(3 * 2)
    assert kendall([1, 2, 3], [1, 5, 5]) == pytest.approx(2 / np.sqrt(6))
    assert spearman([1, 2, 3], [7, 7, 7]) == 0.0 and kendall([1, 2, 3], [7, 7, 7]) == 0.0


def test_a_random_prediction_is_chance_on_average():
    rng = np.random.default_rng(0)
    truth = np.arange(10.0)
    rhos = [spearman(truth, rng.permutation(10)) for _ in range(400)]
    accs = [pairwise_accuracy(truth, rng.permutation(10)) for _ in range(400)]
    assert abs(np.mean(rhos)) < 0.05 and abs(np.mean(accs) - 0.5) < 0.03


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="same length >= 2"):
        spearman([1, 2, 3], [1, 2])
    with pytest.raises(ValueError, match="finite"):
        kendall([1, np.nan], [1, 2])


def test_pearson_and_mean_maximum_rank_violation_by_hand():
    truth = [1.0, 2.0, 3.0, 4.0]
    assert pearson(truth, [2, 4, 6, 8]) == pytest.approx(1.0) and pearson(truth, [5, 5, 5, 5]) == 0.0
    assert pearson(truth, [1, 2, 3, 10]) == pytest.approx(np.corrcoef(truth, [1, 2, 3, 10])[0, 1])
    assert mean_maximum_rank_violation(truth, [10, 20, 30, 40]) == 0.0
    # the last two swapped: each of them has a violation of |3 - 4| = 1, the others none
    assert mean_maximum_rank_violation(truth, [1, 2, 4, 3]) == pytest.approx(0.5)
    # fully reversed: policy i's largest violated gap is its distance to the furthest policy (3, 2, 2, 3)
    assert mean_maximum_rank_violation(truth, [4, 3, 2, 1]) == pytest.approx(2.5)
    # a tie in the prediction only is a violation (SIMPLER's strict comparisons), seen from the higher policy
    assert mean_maximum_rank_violation(truth, [1, 1, 3, 4]) == pytest.approx(0.25)


def test_spearman_p_value_counts_orderings():
    assert spearman_p_value([1, 2, 3], [1, 2, 3]) == pytest.approx(1 / 6)  # only the observed ordering
    assert spearman_p_value([1, 2, 3], [3, 2, 1]) == 1.0
    # one adjacent swap of eight: the identity and the 7 single adjacent swaps reach rho >= its rho
    assert spearman_p_value(range(8), [0, 1, 2, 3, 4, 5, 7, 6]) == pytest.approx(8 / 40320)
    # twelve policies: random orderings, the observed one counted once more
    p = spearman_p_value(range(12), range(12), num_permutations=1000)
    assert p == pytest.approx(1 / 1001)
    rng = np.random.default_rng(1)
    assert 0.2 < np.mean([spearman_p_value(range(6), rng.permutation(6)) for _ in range(50)]) < 0.8


def test_bootstrap_interval_over_starts():
    rng = np.random.default_rng(0)
    truth_SN = np.tile(np.arange(6.0), (10, 1))
    # the same returns at every start: every resample gives the same rho
    assert bootstrap_interval(spearman, truth_SN, truth_SN * 2) == pytest.approx((1.0, 1.0))
    noisy_SN = truth_SN + rng.normal(0, 3, truth_SN.shape)
    low, high = bootstrap_interval(spearman, truth_SN, noisy_SN)
    assert -1 <= low < spearman(truth_SN.mean(0), noisy_SN.mean(0)) < high <= 1
    assert (low, high) == bootstrap_interval(spearman, truth_SN, noisy_SN)  # seeded
    narrow = bootstrap_interval(spearman, truth_SN, truth_SN + rng.normal(0, 0.5, truth_SN.shape))
    assert narrow[1] - narrow[0] < high - low
    with pytest.raises(ValueError, match="one shape"):
        bootstrap_interval(spearman, truth_SN, truth_SN[:, :3])
