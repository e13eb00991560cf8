"""Wilson score interval (``waveforest.stats.proportion``)."""

import math

import pytest

from waveforest.stats.proportion import wilson_interval


def test_wilson_interval_known_values():
    # 8 of 10: the textbook 95 % Wilson interval 0.490-0.943
    assert wilson_interval(0.8, 10) == pytest.approx((0.4902, 0.9433), abs=5e-4)
    lo, hi = wilson_interval(0.0, 20)  # never below 0, and not degenerate at 0
    assert lo == 0.0 and 0.1 < hi < 0.2


def test_wilson_interval_narrows_with_n_and_needs_trials():
    assert wilson_interval(0.7, 400)[1] - wilson_interval(0.7, 400)[0] < wilson_interval(0.7, 40)[1] - wilson_interval(0.7, 40)[0]
    assert all(math.isnan(v) for v in wilson_interval(0.5, 0))
