"""evaluation/ranking.py against values computed by hand (and scipy's definitions, where they agree)."""
import numpy as np
import pytest

from evaluation.ranking import average_ranks, kendall, pairwise_accuracy, regret_at_1, spearman


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
