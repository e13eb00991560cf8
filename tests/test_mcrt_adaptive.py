"""The adaptive ray budget of ``mcrt.trace`` (docs/method.md §(d), "Ray budget")."""

import math

import numpy as np
import pytest
from fixtures import scenes as syn

from waveforest.mcrt import Beams, prepare, trace
from waveforest.mcrt.tracer import BATCHES, GROWTH, next_budget, waveform_error
from waveforest.sensor.system_waveform import gaussian_system_waveform

RHO, TAU, RHO_G = 0.3, 0.6, 0.8
KERNEL = gaussian_system_waveform(7.2, 1.0).s  # unit peak: noise in units of sigma
NADIR = dict(viewed_diameter_m=30.0, max_order=7)


def _sheet_total(rho=RHO, tau=TAU, rho_g=RHO_G, orders=7) -> float:
    """Exact total sigma of a sheet over a ground at nadir (tests/test_mcrt_analytic.py)."""
    total = rho / math.pi
    for order in range(3, orders + 1, 2):
        k = (order - 1) // 2
        total += tau / (rho + tau) * (rho / (rho + tau)) ** (k - 1) * (rho + tau) ** k * rho_g**k * tau / math.pi
    return total


@pytest.fixture(scope="module")
def sheet():
    return prepare(syn.sheet_over_ground(40.0, 0.05, RHO, TAU, RHO_G))


def _beams(n):
    return Beams.toward(np.zeros((n, 3)) + [0, 0, 0.05], 1000.0, footprint_m=0.2)


def test_waveform_error_of_known_replicate_spread():
    rng = np.random.default_rng(0)
    n, k, bins = 200, 8, 400
    signal = np.zeros(bins)
    signal[100:300] = 1.0
    sd = 0.05
    reps = signal[None, None, :] + sd * rng.standard_normal((n, k, bins))
    noise = np.full(n, 0.5)
    # kernel [1] on a 1-ns step: samples are sums of 20 bins, SD sd sqrt(20), mean of k
    err = waveform_error(reps, np.array([1.0]), noise, 0.05)
    expected = sd * math.sqrt(20) / math.sqrt(k) / 0.5
    assert np.median(err) == pytest.approx(expected, rel=0.05)
    assert np.all(waveform_error(reps * 0, np.array([1.0]), noise, 0.05) == 0.0)  # no signal: no support


def test_fixed_budget_records_its_rays(sheet):
    res = trace(sheet, _beams(3), n_rays=300, seed=1, sampler="sobol", roulette=0.5, **NADIR)
    assert res.n_rays == 300 and res.rays.tolist() == [300, 300, 300]


def test_adaptive_budget_needs_the_sensor(sheet):
    with pytest.raises(ValueError, match="kernel"):
        trace(sheet, _beams(1), n_rays=1, seed=1, sampler="sobol", roulette=0.5, tolerance=0.3)
    with pytest.raises(ValueError, match="tolerance"):
        trace(sheet, _beams(1), n_rays=1, seed=1, sampler="sobol", roulette=0.5, tolerance=-1.0,
              kernel=KERNEL, noise=1.0)


def _adaptive(scene, beams, seed, tol=0.3, noise=2e-3, **kw):
    args = dict(n_rays=1, seed=seed, sampler="sobol", roulette=0.5, tolerance=tol, kernel=KERNEL, noise=noise,
                min_rays=256, max_rays=65536, **NADIR)
    args.update(kw)
    return trace(scene, beams, **args)


def test_adaptive_rays_between_bounds_and_stop_at_the_tolerance(sheet):
    beams = _beams(6)
    res = _adaptive(sheet, beams, 3)
    assert np.all((res.rays >= 256) & (res.rays <= 65536))
    grid = 2 ** (np.floor(np.log2(res.rays)).astype(np.int64) - 2)  # four counts per octave
    assert np.all(res.rays % grid == 0), res.rays
    assert res.rays.min() < res.rays.max() or res.rays[0] > 256  # it did adapt
    # tighter tolerance: more rays
    tight = _adaptive(sheet, beams, 3, tol=0.1)
    assert tight.rays.mean() > 2 * res.rays.mean()
    # a noise far above the signal: the first round suffices
    assert _adaptive(sheet, beams, 3, noise=1e3).rays.tolist() == [256] * 6
    # first-hit counts add up over the replicates and rounds
    assert np.array_equal(res.first_hit_counts.sum(axis=1), res.rays)


def test_next_budget_asks_for_the_rays_the_error_calls_for():
    done = np.array([1024, 1024, 1024, 4096, 16384])
    ratio = np.array([1.05, 1.5, 3.0, 1.2, 1.01])
    got = next_budget(done, ratio, 2**15)
    need = done * ratio**2
    assert np.all(got >= np.minimum(need, GROWTH * done)) and np.all(got > done)
    assert np.all(got <= np.maximum(1.25 * np.minimum(need, GROWTH * done), done + done // 4))  # <= a quarter octave over
    assert np.all(got % BATCHES == 0) and got.tolist()[2] == GROWTH * 1024 and got[-1] <= 2**15
    assert next_budget(np.array([2**15 - 8]), np.array([10.0]), 2**15).tolist() == [2**15]


def test_a_pulse_stopped_at_n_rays_is_the_fixed_budget_of_n_rays():
    scene = prepare(syn.random_leaves(2.0, (0.0, 1.0), 3.0, 4e-3, seed=2), quality="medium")
    beams = Beams.toward(np.zeros((3, 3)), 1000.0, footprint_m=0.2)
    res = trace(scene, beams, n_rays=1, seed=5, sampler="sobol", roulette=0.5, max_order=5, tolerance=0.3,
                kernel=KERNEL, noise=1e-3, min_rays=512, max_rays=2**14)
    for i, n in enumerate(res.rays):  # the same keys and rays as a fixed budget of n rays
        fixed = trace(scene, beams, n_rays=int(n), seed=5, sampler="sobol", roulette=0.5, max_order=5)
        np.testing.assert_allclose(res.sigma[i], fixed.sigma[i], rtol=1e-9, atol=1e-15)
        np.testing.assert_array_equal(res.first_hit_counts[i], fixed.first_hit_counts[i])


def test_adaptive_is_independent_of_threads_and_chunking(sheet):
    beams = _beams(5)
    a = _adaptive(sheet, beams, 4)
    b = _adaptive(sheet, beams, 4, chunk_rays=1000, threads=1)
    c = _adaptive(sheet, beams, 4, parallel="rays", threads=2)
    for r in (b, c):
        assert np.array_equal(a.rays, r.rays)
        np.testing.assert_array_equal(a.sigma, r.sigma)


def test_adaptive_stopping_adds_no_bias_beyond_the_tolerance(sheet):
    """Mean over 96 pulses-seeds of the adaptive total sigma is the exact total; its bias on the
    recorded waveform is well below tolerance x noise (the test resolves about 0.1 of it)."""
    tol, noise = 0.3, 2e-3
    totals = []
    for seed in range(6):
        res = _adaptive(sheet, _beams(16), seed, tol=tol, noise=noise)
        totals.extend(res.total.tolist())
    totals = np.array(totals)
    exact = _sheet_total()
    se = totals.std(ddof=1) / math.sqrt(totals.size)
    assert abs(totals.mean() - exact) < 4 * se + 1e-12, (totals.mean(), exact, se)
    # the whole sigma lies within 0.5 ns: the waveform's bias is (mean - exact) x the kernel's peak (1)
    assert abs(totals.mean() - exact) < 0.5 * tol * noise


def test_adaptive_error_at_the_tolerance_on_a_leaf_canopy():
    """Over seeds, the recorded waveform's actual error (against a reference) stays near the tolerance."""
    scene = prepare(syn.random_leaves(2.0, (0.0, 1.0), 3.0, 4e-3, seed=2), quality="medium")
    beams = Beams.toward(np.zeros((4, 3)), 1000.0, footprint_m=0.2)
    ref = trace(scene, beams[:1], n_rays=2**18, seed=99, sampler="sobol", roulette=0.0, max_order=5)
    w_ref = np.convolve(ref.sigma[0], KERNEL)
    tol, noise = 0.3, 1e-3
    errs = []
    for seed in range(3):
        res = trace(scene, beams, n_rays=1, seed=seed, sampler="sobol", roulette=0.5, max_order=5,
                    tolerance=tol, kernel=KERNEL, noise=noise, min_rays=512, max_rays=2**16)
        for s in res.sigma:
            w = np.convolve(s, KERNEL)
            sup = w_ref >= 0.1 * noise
            errs.append(math.sqrt(np.mean((w[sup] - w_ref[sup]) ** 2)) / noise)
    errs = np.array(errs)
    assert math.sqrt(np.mean(errs**2)) < 1.5 * tol, errs


def test_budget_in_sensor_terms():
    """MCRTSetup.budget: noise s R^2 / g in the units of S (x) sigma; none without a tolerance."""
    from dataclasses import replace

    from waveforest.config import load
    from waveforest.settings import mcrt_setup

    cfg = load()
    setup = mcrt_setup(cfg)
    assert setup.tolerance == cfg["mcrt"]["tolerance"]
    assert mcrt_setup(cfg, n_rays=500).tolerance is None  # a section's own n_rays fixes the rays
    system = gaussian_system_waveform(7.2, 1e9)
    b = setup.budget(system, 1.5, np.array([1000.0, 2000.0]), gain=np.array([1.0, 2.0]))
    np.testing.assert_allclose(b["noise"], [1.5e6, 1.5 * 4e6 / 2])
    assert b["kernel"] is not None and b["min_rays"] == cfg["mcrt"]["min_rays"]
    assert replace(setup, tolerance=None).budget(system, 1.5, 1000.0) == {}


def test_campaign_budget_follows_the_true_sensor():
    from waveforest.campaign.params import load_datasets
    from waveforest.campaign.site_trace import AGC_HIGH_SD, SiteJob, TraceSettings, site_budget
    from waveforest.campaign.truth_sensor import TruthSensor

    sensors = tuple(TruthSensor.from_row(r) for _, r in load_datasets(["2010_12_1", "2012_10_1"]).iterrows())
    job = SiteJob("s", "sample", "birch", 3.0, 0.0, 0.0, 0.0, 0.0, np.zeros((2, 3)), np.zeros((2, 3)),
                  np.full(2, 0.15), np.array([1000.0, 1500.0]), np.array([0, 1]), np.arange(2))
    st = TraceSettings(seed=0, n_rays=256, max_order=5, viewed_diameter_m=5.0, specular=0.0, hotspot=1.0,
                       trigger_loss=0.0, ground_rho=0.3, lai_jitter=0.0, vegetation_effects=(), sensors=sensors,
                       bvh_quality="medium", sampler="sobol", roulette=0.5, tolerance=0.33, max_rays=4096)
    b = site_budget(job, st)
    assert b["tolerance"] == 0.33 and b["min_rays"] == 256 and b["max_rays"] == 4096
    assert b["kernel"].max() == pytest.approx(1.0)
    for i, t in enumerate(sensors):
        g = t.agc.gain(t.agc.bg_mean + AGC_HIGH_SD * t.agc.bg_sd)
        assert b["noise"][i] == pytest.approx(t.noise_sd_dn * job.range_m[i] ** 2 / (g * t.system.s.max()))
    assert site_budget(job, TraceSettings(**{**st.__dict__, "tolerance": None})) == {}
