"""Numba kernels against the NumPy reference, sampling laws, conservation and reproducibility."""

import math

import numba
import numpy as np
import pytest
from fixtures import scenes as syn
from reference_mcrt import reference_trace
from scipy import stats

from waveforest.effects import SPECULAR_PHONG_EXPONENT as PHONG
from waveforest.mcrt import Beams, prepare, trace
from waveforest.mcrt.kernels import BeamFrame, Rays, Scattered, accumulate, beam_keys, scatter

# with NUMBA_DISABLE_JIT=1 the uint64 hash runs on NumPy scalars, which warn on (intended) wrap-around
pytestmark = pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")

REF_RTOL = 1e-6  # float32 Embree frame vs float64 reference
KS_P = 1e-3  # smallest accepted Kolmogorov-Smirnov p-value of a sampling law
VAR_P = 1e-3  # two-sided tail probability of the chi-square test of a Monte Carlo variance
N_SE = 4.0


@pytest.fixture(scope="module")
def small_canopy():
    return syn.random_leaves(2.0, (0.1, 0.6), 1.0, 4e-3, seed=5)


def _beams():
    far = np.array([-300.0, 200.0, -2900.0])
    return Beams(np.array([[0.0, 0.0, 800.0], [300.0, -200.0, 2900.0]]),
                 np.array([[0.0, 0.0, -1.0], far / np.linalg.norm(far)]), [0.5, 0.4],
                 [np.nan, np.linalg.norm(far)])


@pytest.mark.parametrize("backend", ["numpy", "embree", "embreex"])
@pytest.mark.parametrize("specular,hotspot", [(0.0, 1.0), (0.3, 1.3)])
def test_kernels_match_the_numpy_reference(small_canopy, backend, specular, hotspot):
    beams = _beams()
    kw = dict(n_rays=120, max_order=5, bin_ns=0.05, viewed_diameter_m=0.8, seed=7)
    res = trace(prepare(small_canopy, backend=backend), beams, specular=specular, hotspot=hotspot,
                window_ns=20.0, sampler="random", roulette=0.0, **kw)
    ref = reference_trace(small_canopy, beams.origin, beams.direction, beams.footprint_m, beams.range_m,
                          kw["n_rays"], kw["max_order"], kw["bin_ns"], kw["viewed_diameter_m"], kw["seed"],
                          specular, hotspot, window_ns=20.0)
    np.testing.assert_array_equal(res.first_hit_counts, ref["first_hit_counts"])
    np.testing.assert_allclose(res.t0_ns, ref["t0_ns"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(res.order_totals, ref["order_totals"], rtol=REF_RTOL, atol=1e-12)
    np.testing.assert_allclose(res.sigma, ref["sigma"], rtol=REF_RTOL, atol=1e-12)
    np.testing.assert_allclose(res.sigma_dropped, ref["dropped"], rtol=REF_RTOL, atol=1e-12)
    assert np.count_nonzero(res.order_totals[:, 1:]) >= 6  # multiple scattering exercised


def test_conservation_and_by_order(small_canopy):
    res = trace(small_canopy, _beams(), n_rays=3000, max_order=6, viewed_diameter_m=0.8, seed=3,
                by_order=True, window_ns=12.0, sampler="random", roulette=0.0)
    assert np.all(res.first_hit_counts.sum(axis=1) == 3000)
    np.testing.assert_allclose(res.sigma.sum(axis=1) + res.sigma_dropped, res.total, rtol=1e-12)
    np.testing.assert_allclose(res.sigma_by_order.sum(axis=1), res.sigma, rtol=1e-12, atol=1e-15)
    binned = res.sigma_by_order.sum(axis=2)
    assert np.all(binned <= res.order_totals * (1 + 1e-12))
    df = res.frame(1)
    assert list(df.columns[:3]) == ["time_ns", "range_m", "sigma"] and "sigma_order_6" in df
    np.testing.assert_allclose(df["sigma"].sum(), res.sigma[1].sum())


def test_short_window_drops_late_light_but_counts_it():
    sc = syn.sheet_over_ground(40.0, 0.5, 0.47, 0.5, 0.3)
    beams = Beams.toward([0, 0, 0.5], 1000.0, footprint_m=0.2)
    full = trace(sc, beams, n_rays=3000, max_order=5, viewed_diameter_m=30.0, seed=2, sampler="random", roulette=0.0)
    short = trace(sc, beams, n_rays=3000, max_order=5, viewed_diameter_m=30.0, seed=2, window_ns=2.0,
                  sampler="random", roulette=0.0)
    assert full.sigma_dropped[0] == 0.0 and short.sigma_dropped[0] > 0.0
    assert short.n_bins == 40
    np.testing.assert_allclose(short.order_totals, full.order_totals, rtol=1e-12)
    np.testing.assert_allclose(short.sigma.sum() + short.sigma_dropped[0], full.total[0], rtol=1e-12)
    # bins of the short window equal the first bins of the full one
    np.testing.assert_allclose(short.sigma[0], full.sigma[0, :40], rtol=1e-12)


def test_same_seed_identical_whatever_threads_and_chunks(small_canopy):
    beams = Beams.toward(np.array([[0.1 * i, 0.0, 0.0] for i in range(5)]), 1000.0, 8.0, 30.0, footprint_m=0.3)
    kw = dict(n_rays=2000, max_order=6, viewed_diameter_m=1.0, seed=42, sampler="random", roulette=0.0)
    a = trace(small_canopy, beams, **kw)
    b = trace(small_canopy, beams, chunk_rays=2000, threads=1, **kw)
    prev = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        c = trace(small_canopy, beams, **kw)
    finally:
        numba.set_num_threads(prev)
    for other in (b, c):
        assert np.array_equal(a.sigma, other.sigma)
        assert np.array_equal(a.order_totals, other.order_totals)
        assert np.array_equal(a.first_hit_counts, other.first_hit_counts)
    rng_a = trace(small_canopy, beams, **{**kw, "seed": np.random.default_rng(9)})
    rng_b = trace(small_canopy, beams, **{**kw, "seed": np.random.default_rng(9)})
    assert np.array_equal(rng_a.sigma, rng_b.sigma)


def test_different_seeds_differ_by_the_monte_carlo_error():
    """Across seeds, the order-3 total of a sheet over a ground scatters with the binomial
    Monte Carlo variance: its sample variance lies in the chi-square interval of that variance."""
    rho, tau, rho_g, n, k = 0.47, 0.5, 0.3, 5000, 12
    sc = prepare(syn.sheet_over_ground(40.0, 0.05, rho, tau, rho_g))
    beams = Beams.toward([0, 0, 0.05], 1000.0, footprint_m=0.2)
    runs = [trace(sc, beams, n_rays=n, max_order=3, viewed_diameter_m=30.0, seed=s, sampler="random",
                  roulette=0.0) for s in range(k)]
    assert not np.array_equal(runs[0].sigma, runs[1].sigma)
    # order 3: a ray contributes c with probability p = tau / (rho + tau)
    p = tau / (rho + tau)
    c = (rho + tau) * rho_g * tau / math.pi
    var = c**2 * p * (1 - p) / n
    got = np.array([r.order_totals[0, 2] for r in runs])
    assert abs(got.mean() - c * p) < N_SE * math.sqrt(var / k)
    ratio = got.var(ddof=1) / var  # ~ chi2(k - 1) / (k - 1)
    lo, hi = stats.chi2.ppf([VAR_P / 2, 1 - VAR_P / 2], k - 1) / (k - 1)
    assert lo < ratio < hi, f"sample variance / binomial variance = {ratio:.3g}, expected in ({lo:.3g}, {hi:.3g})"


def _plane_rays(m, zenith_deg=0.0):
    d = np.array([math.sin(math.radians(zenith_deg)), 0.0, -math.cos(math.radians(zenith_deg))])
    o = np.zeros((m, 3), np.float32) - (d * 0.5).astype(np.float32)
    return Rays(o, np.tile(d.astype(np.float32), (m, 1)), np.full(m, 1.0 / m), np.zeros(m),
                np.zeros(m, np.int32), np.arange(m, dtype=np.int32))


def _one_order(sc, rays, specular=0.0):
    ps = prepare(sc)
    frame = BeamFrame(np.array([[0.0, 0.0, 1000.0]]), np.array([[0.0, 0.0, -1.0]]), np.array([0.0]),
                      beam_keys(17, np.array([0])))
    t, p = ps.intersector.intersect(rays.origin, rays.direction)
    assert np.all(p >= 0)
    return scatter(1, False, rays, t, p, ps, frame, 10, 0.05, 5.0, specular=specular, phong_n=PHONG)


@pytest.mark.parametrize("rho,tau", [(0.6, 0.0), (0.3, 0.6)])
def test_new_directions_are_cosine_weighted_on_the_right_side(rho, tau):
    m = 20000
    sc = syn.plane(4.0, 0.0, rho=rho, tau=tau, kind=1)
    out = _one_order(sc, _plane_rays(m, 25.0))
    assert np.all(out.alive)
    np.testing.assert_allclose(out.power, (rho + tau) / m)
    cz = out.direction[:, 2].astype(float)
    up = cz > 0
    # reflected (lit side, up) with probability rho / (rho + tau)
    frac = up.mean()
    p = rho / (rho + tau)
    assert abs(frac - p) <= N_SE * math.sqrt(p * (1 - p) / m) + 1e-12
    # cos(theta) of a cosine-weighted direction: cos^2 is uniform on [0, 1]
    assert stats.kstest(cz**2, "uniform").pvalue > KS_P
    # azimuth uniform
    az = np.arctan2(out.direction[:, 1], out.direction[:, 0])
    assert stats.kstest((az + np.pi) / (2 * np.pi), "uniform").pvalue > KS_P
    # origins offset along the normal to the outgoing side
    np.testing.assert_allclose(np.sign(out.origin[:, 2]), np.sign(cz))
    np.testing.assert_allclose(np.linalg.norm(out.direction, axis=1), 1.0, atol=1e-6)


def _lobe_albedo(theta_in):
    """Directional albedo of the Phong lobe, (n+2)/(2 pi) int cos^n(alpha) cos(theta) dw, by quadrature."""
    th, ph = np.meshgrid(np.linspace(0, np.pi / 2, 1501), np.linspace(0, 2 * np.pi, 1501), indexing="ij")
    w = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    mirror = np.array([np.sin(theta_in), 0.0, np.cos(theta_in)])
    ca = np.clip(w @ mirror, 0, None)
    f = (PHONG + 2) / (2 * np.pi) * ca**PHONG * np.cos(th) * np.sin(th)
    return np.trapezoid(np.trapezoid(f, ph[0], axis=1), th[:, 0])


@pytest.mark.parametrize("zenith", [0.0, 60.0])
def test_specular_lobe_sampling_conserves_the_lobe_albedo(zenith):
    """Pure Phong leaves (s = 1, tau = 0): mean reflected power = rho x the lobe's albedo."""
    m, rho = 40000, 0.5
    sc = syn.plane(4.0, 0.0, rho=rho, tau=0.0, kind=1)
    out = _one_order(sc, _plane_rays(m, zenith), specular=1.0)
    total = out.power[out.alive].sum()
    w = np.where(out.alive, out.power, 0.0) * m
    se = w.std() / math.sqrt(m)
    expected = rho * _lobe_albedo(math.radians(zenith))
    assert abs(total - expected) < N_SE * se + 1e-9
    if zenith == 0.0:
        assert expected == pytest.approx(rho, rel=1e-4)
    # lobe directions cluster around the mirror direction
    mirror = np.array([math.sin(math.radians(zenith)), 0.0, math.cos(math.radians(zenith))])
    ca = out.direction[out.alive].astype(float) @ mirror
    assert np.median(ca) > math.cos(math.radians(20.0))


def test_accumulate_adds_serially_and_validates():
    acc = np.zeros((2, 1, 4))
    dropped = np.zeros(2)
    totals = np.zeros((2, 3))
    beam = np.array([0, 1, 1, 0], np.int32)
    value = np.array([1.0, 2.0, 3.0, 4.0])
    bins = np.array([0, 3, -1, 0])
    accumulate(np.array([0, 1, 2, 3]), beam, value, bins, 2, acc, dropped, totals, by_order=False)
    assert acc[0, 0].tolist() == [5.0, 0, 0, 0] and acc[1, 0].tolist() == [0, 0, 0, 2.0]
    assert dropped.tolist() == [0.0, 3.0] and totals[:, 1].tolist() == [5.0, 5.0]
    with pytest.raises(ValueError, match="order"):
        accumulate(np.array([0]), beam, value, bins, 4, acc, dropped, totals, by_order=False)
    with pytest.raises(ValueError, match="layers"):
        accumulate(np.array([0]), beam, value, bins, 2, acc, dropped, totals, by_order=True)
    with pytest.raises(ValueError, match="window"):
        accumulate(np.array([0]), beam, value, np.array([9, 0, 0, 0]), 1, acc, dropped, totals, False)


def test_scatter_validates_inputs():
    sc = prepare(syn.plane(2.0))
    rays = _plane_rays(4)
    frame = BeamFrame(np.zeros((1, 3)), np.array([[0.0, 0, -1]]), np.zeros(1), beam_keys(1, np.array([0])))
    t = np.ones(4, np.float32)
    with pytest.raises(ValueError, match="prim"):
        scatter(1, False, rays, t, np.array([0, 0, 0, 5], np.int32), sc, frame, 10, 0.05, 5.0)
    with pytest.raises(ValueError, match="float32 and int32"):
        scatter(1, False, rays, t.astype(float), np.zeros(4, np.int32), sc, frame, 10, 0.05, 5.0)
    with pytest.raises(ValueError, match="specular"):
        scatter(1, False, rays, t, np.zeros(4, np.int32), sc, frame, 10, 0.05, 5.0, specular=2.0)
    with pytest.raises(ValueError, match="out"):
        scatter(1, False, rays, t, np.zeros(4, np.int32), sc, frame, 10, 0.05, 5.0, out=Scattered.empty(2))


VALID = dict(n_rays=100, sampler="random", roulette=0.0)
"""The arguments ``trace`` needs besides the scene and the beams."""


@pytest.mark.parametrize(
    "kwargs,match",
    [({"n_rays": 0}, "n_rays"), ({"max_order": 0}, "max_order"), ({"bin_ns": 0.0}, "bin_ns"),
     ({"specular": 1.5}, "specular"), ({"hotspot": -1.0}, "hotspot"), ({"seed": -3}, "seed"),
     ({"window_ns": np.inf}, "window_ns"), ({"sampler": "halton"}, "sampler"), ({"roulette": 1.5}, "roulette")],
)
def test_trace_validates_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        trace(syn.plane(2.0), Beams.toward([0, 0, 0], 1000.0, footprint_m=0.1), **{**VALID, **kwargs})
    with pytest.raises(TypeError, match="Beams"):
        trace(syn.plane(2.0), np.zeros((1, 3)), **VALID)
