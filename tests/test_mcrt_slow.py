"""Full-size MCRT runs (slow): the benchmark canopy and a finer gap-fraction check."""

import math

import numpy as np
import pytest
from fixtures import scenes as syn

from waveforest.mcrt import Beams, prepare, trace

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def canopy():
    """The benchmark canopy: LAI 3.35, 1.2 m tall, 6 x 6 m, ~180,000 leaves."""
    return prepare(syn.random_leaves(3.35, (0.0, 1.2), 6.0, 6.7e-4, seed=1))


def test_full_canopy_modes_agree_and_conserve(canopy):
    rng = np.random.default_rng(0)
    n = 4
    beams = Beams.toward(np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.zeros(n)]), 1200.0,
                         rng.uniform(0, 15, n), rng.uniform(0, 360, n), divergence_mrad=0.15)
    a = trace(canopy, beams, n_rays=30000, max_order=10, seed=3, parallel="pulses", threads=2, sampler="random",
              roulette=0.0)
    b = trace(canopy, beams, n_rays=30000, max_order=10, seed=3, parallel="rays", threads=2, sampler="random",
              roulette=0.0)
    assert np.array_equal(a.sigma, b.sigma) and np.array_equal(a.order_totals, b.order_totals)
    assert np.all(a.first_hit_counts.sum(axis=1) == 30000)
    np.testing.assert_allclose(a.sigma.sum(axis=1) + a.sigma_dropped, a.total, rtol=1e-12)
    # every order contributes, and light decays with order beyond the second
    assert np.all(a.order_totals > 0)
    assert np.all(np.diff(a.order_totals[:, 1:], axis=1) < 0)
    # at most the LAI-3.35 gap (exp(-0.5 L / cos 15 deg) ~ 0.18) reaches the ground first
    gap = a.first_hit_counts[:, 0] / 30000
    assert np.all((gap > 0.08) & (gap < 0.35))


@pytest.mark.parametrize("zenith", [15.0, 45.0])
def test_gap_fraction_many_beams(zenith):
    lai = 3.0
    ps = prepare(syn.random_leaves(lai, (0.2, 0.8), 8.0, 5e-4, seed=21))
    g = np.linspace(-2.0, 2.0, 6)
    targets = np.array([[x, y, 0.0] for x in g for y in g])
    res = trace(ps, Beams.toward(targets, 1000.0, zenith, 10.0, footprint_m=0.3), n_rays=3000, max_order=1, seed=8,
                sampler="random", roulette=0.0)
    gap = res.first_hit_counts[:, 0] / 3000
    se = gap.std(ddof=1) / math.sqrt(len(gap))
    expected = math.exp(-0.5 * lai / math.cos(math.radians(zenith)))
    assert abs(gap.mean() - expected) < 3 * se
