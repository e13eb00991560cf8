"""Intervals of a proportion and of a quantile (``waveforest.stats.proportion``)."""

import math

import numpy as np
import pytest

from waveforest.stats.proportion import quantile_ranks, wilson_interval


def test_wilson_interval_known_values():
    # 8 of 10: the textbook 95 % Wilson interval 0.490-0.943
    assert wilson_interval(0.8, 10) == pytest.approx((0.4902, 0.9433), abs=5e-4)
    lo, hi = wilson_interval(0.0, 20)  # never below 0, and not degenerate at 0
    assert lo == 0.0 and 0.1 < hi < 0.2


def test_wilson_interval_narrows_with_n_and_needs_trials():
    assert wilson_interval(0.7, 400)[1] - wilson_interval(0.7, 400)[0] < wilson_interval(0.7, 40)[1] - wilson_interval(0.7, 40)[0]
    assert all(math.isnan(v) for v in wilson_interval(0.5, 0))


def _binom_cdf(k: int, n: int, p: float) -> float:
    return sum(math.comb(n, i) * p**i * (1 - p) ** (n - i) for i in range(k + 1))


def test_quantile_ranks_known_values_and_tails():
    # 20 draws, the 0.8-quantile: the 12th and the 20th order statistic (miss 0.0100 below, 0.0115 above)
    assert quantile_ranks(20, 0.8) == (12, 20)
    assert quantile_ranks(5, 0.5) == (0, 6)  # five draws cannot bound a median at 95 %
    for n, p in ((20, 0.8), (40, 0.8), (100, 0.5), (13, 0.3)):
        r, s = quantile_ranks(n, p)
        below = _binom_cdf(r - 1, n, p) if r >= 1 else 0.0  # P(X_(r) > q)
        above = 1 - _binom_cdf(s - 1, n, p) if s <= n else 0.0  # P(X_(s) < q)
        assert below <= 0.025 and above <= 0.025
        # each end as tight as the tail allows: one rank further in misses more than 2.5 %
        assert _binom_cdf(r, n, p) > 0.025 and 1 - _binom_cdf(s - 2, n, p) > 0.025
    with pytest.raises(ValueError):
        quantile_ranks(20, 1.0)


def test_quantile_interval_covers_the_quantile_of_any_distribution():
    """Distribution-free: over 4,000 seeded sets of 20 draws from a skewed law, [X_(12), X_(20)]
    holds its 0.8-quantile in 1 - 0.0100 - 0.0115 = 97.85 % of the sets (binomial SE 0.23 %)."""
    rng = np.random.default_rng(7)
    x = np.sort(rng.exponential(size=(4000, 20)), axis=1)
    q = -math.log(0.2)  # the exponential's 0.8-quantile
    r, s = quantile_ranks(20, 0.8)
    covered = np.mean((x[:, r - 1] <= q) & (q <= x[:, s - 1]))
    assert covered == pytest.approx(1 - _binom_cdf(11, 20, 0.8) - 0.8**20, abs=0.008)
