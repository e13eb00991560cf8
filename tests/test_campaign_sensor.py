"""The virtual ALS60's true sensor: system pulse, DR discriminator, AGC loop, recording."""

from __future__ import annotations

import numpy as np
import pytest
from reference_campaign import agc_loop_reference, dr_cfd_reference, sample_reference
from scipy.integrate import quad

from waveforest.campaign.agc_loop import AGCParams, agc_sequence
from waveforest.campaign.dr_cfd import AMP_POST_FWHM, AMP_PRE_FWHM, SEARCH_FWHM, dr_cfd
from waveforest.campaign.params import load_datasets
from waveforest.campaign.system_pulse import emg, fwhm, true_system_waveform
from waveforest.campaign.truth_sensor import TruthSensor, record, unit_gain_peaks
from waveforest.constants import BIN_NS, C_M_PER_NS, RANGE_PER_NS
from waveforest.sensor.signal import sample_analog

FWHM_TOL = 0.005
"""Relative tolerance of the tabulated pulse width."""


@pytest.fixture(scope="module")
def sensor():
    return TruthSensor.from_row(load_datasets(["2010_12_1"]).iloc[0])


def spike_sigma(n, rho=0.3, bins=400, at=100):
    sig = np.zeros((n, bins))
    sig[:, at] = rho / np.pi
    return sig


def spike_t0(range_m, at=100):
    """t0 so that the centre of bin ``at`` is the two-way time of ``range_m``."""
    return 2 * np.asarray(range_m) / C_M_PER_NS - (at + 0.5) * BIN_NS


# -- system pulse --------------------------------------------------------------------------

def test_emg_is_a_density_and_tends_to_a_gaussian():
    assert quad(lambda t: emg(np.array([t]), 1.3, 0.7)[0], -30, 60)[0] == pytest.approx(1.0, abs=1e-7)
    t = np.linspace(-5, 5, 101)
    gauss = np.exp(-t**2 / 2) / np.sqrt(2 * np.pi)
    shifted = emg(t + 1e-3, 1.0, 1e-3)  # the mean of the EMG is sigma-mean + tau
    assert np.allclose(shifted, gauss, atol=2e-4)


@pytest.mark.parametrize("width, tail", [(7.2, 1.0), (10.1, 0.8), (3.0, 1.3)])
def test_system_pulse_has_the_requested_fwhm_peak_and_a_tail(width, tail):
    w = true_system_waveform(width, tail, 0.02, 2.2, 1e9, cfd_fraction=0.35, cfd_delay_fwhm=0.5)
    assert w.fwhm_ns == pytest.approx(width, rel=FWHM_TOL)
    assert fwhm(w.t_ns, w.s) == pytest.approx(width, rel=FWHM_TOL)
    assert w.peak == pytest.approx(1e9)
    assert np.allclose(np.diff(w.t_ns), BIN_NS)
    assert w.t_ns[w.i0] == pytest.approx(0.0, abs=1e-12)
    # asymmetric: the fall from the peak to a tenth of it takes longer than the rise
    k = int(np.argmax(w.s))
    rise = w.t_ns[k] - w.t_ns[np.flatnonzero(w.s[:k] < 0.1 * w.peak)[-1]]
    fall = w.t_ns[k + np.flatnonzero(w.s[k:] < 0.1 * w.peak)[0]] - w.t_ns[k]
    assert fall > 1.2 * rise
    # t = 0 is where the sensor's own discriminator fires on a spike
    assert abs(w.cfd_offset_ns) < 1e-3


def test_gaussian_limit_of_the_pulse_width():
    w = true_system_waveform(7.0, 1e-3, 0.0, 2.0, 1.0, cfd_fraction=0.5, cfd_delay_fwhm=0.5)
    sd = 7.0 / (2 * np.sqrt(2 * np.log(2)))
    assert w.sigma_ns == pytest.approx(sd, rel=1e-3)
    # fraction 0.5 and delay FWHM/2: y = x(t - d) - x(t)/2 crosses zero at the Gaussian peak + d/2 - s^2 ln2 / d
    d = 3.5
    t_peak = w.t_ns[np.argmax(w.s)]
    assert t_peak == pytest.approx(-(d / 2 - sd**2 * np.log(2) / d), abs=BIN_NS)


# -- DR discriminator ----------------------------------------------------------------------

def _cfd_args(fwhm_ns=7.2, fraction=0.35, delay_ns=3.6, arm=6.0, dead_ns=10.8):
    return dict(fraction=fraction, delay_ns=delay_ns, arm_dn=arm, dead_time_ns=dead_ns, fwhm_ns=fwhm_ns)


def test_dr_cfd_matches_the_reference_on_random_multi_echo_signals():
    rng = np.random.default_rng(3)
    t = np.arange(3000) * BIN_NS
    x = np.zeros((40, t.size))
    for i in range(40):
        for _ in range(rng.integers(0, 5)):
            x[i] += rng.uniform(2, 150) * np.exp(-0.5 * ((t - rng.uniform(10, 140)) / rng.uniform(1.5, 5)) ** 2)
    args = _cfd_args()
    pos, amp, cnt = dr_cfd(x, **args)
    delay, dead = int(round(3.6 / BIN_NS)), int(round(10.8 / BIN_NS))
    search = int(round(SEARCH_FWHM * 7.2 / BIN_NS))
    pre, post = int(round(AMP_PRE_FWHM * 7.2 / BIN_NS)), int(round(AMP_POST_FWHM * 7.2 / BIN_NS))
    for i in range(40):
        rp, ra = dr_cfd_reference(x[i], 0.35, delay, 6.0, dead, search, pre, post, 4)
        assert cnt[i] == len(rp)
        assert np.allclose(pos[i, :cnt[i]], rp) and np.allclose(amp[i, :cnt[i]], ra)
        assert np.all(np.isnan(pos[i, cnt[i]:]))
    assert cnt.max() >= 2


def test_dr_cfd_time_does_not_depend_on_amplitude_and_respects_the_dead_time():
    t = np.arange(4000) * BIN_NS
    echo = np.exp(-0.5 * ((t - 50.0) / 3.0) ** 2)
    x = np.stack([a * echo for a in (8.0, 30.0, 120.0, 240.0)])
    pos, amp, cnt = dr_cfd(x, **_cfd_args())
    assert np.all(cnt == 1)
    assert np.ptp(pos[:, 0]) < 1e-9
    assert np.allclose(amp[:, 0], [8, 30, 120, 240], rtol=1e-6)
    # analytic crossing of y = x(t - d) - f x(t) for a Gaussian: mu + d/2 + s^2 ln f / d
    expect = 50.0 + 3.6 / 2 + 9.0 * np.log(0.35) / 3.6
    assert pos[0, 0] * BIN_NS == pytest.approx(expect, abs=2e-3)
    # a second echo closer than the dead time is not reported, a farther one is
    near = echo * 100 + 100 * np.exp(-0.5 * ((t - 58.0) / 3.0) ** 2)
    far = echo * 100 + 100 * np.exp(-0.5 * ((t - 70.0) / 3.0) ** 2)
    _, _, c = dr_cfd(np.stack([near, far]), **_cfd_args())
    assert list(c) == [1, 2]


def test_dr_cfd_rejects_bad_input():
    with pytest.raises(ValueError, match="fraction"):
        dr_cfd(np.zeros((1, 10)), **_cfd_args(fraction=1.5))
    with pytest.raises(ValueError, match="2-D"):
        dr_cfd(np.zeros(10), **_cfd_args())


# -- AGC loop ------------------------------------------------------------------------------

def test_gain_law_reference_change_is_exact():
    p = AGCParams.from_row(load_datasets(["2012_20_1"]).iloc[0])
    agc = np.arange(60, 200)
    for a in (100.0, 117.3, 130.0):
        assert np.allclose(p.gain(agc), p.scale_at(a) * (1 + (agc - a) * p.b_at(a)))


def test_agc_loop_matches_the_reference_and_reacts_to_the_signal():
    p = AGCParams.from_row(load_datasets(["2010_12_1"]).iloc[0])
    rng = np.random.default_rng(5)
    n = 600
    strip = np.repeat([0, 1, 2], n // 3)
    t = np.concatenate([np.sort(rng.uniform(0, 60, n // 3)) + 100 * k for k in range(3)])
    a0 = rng.uniform(20, 200, n)
    agc, gain, obs = agc_sequence(t, a0, strip, p, np.random.default_rng(11), saturation_dn=150.0)
    z = np.random.default_rng(11).standard_normal((2, n))
    lo, hi = p.agc_bounds()
    ra, rg, ro = agc_loop_reference(t, a0, strip, z[0], z[1], p, lo, hi, saturation=150.0)
    assert np.array_equal(agc, ra.astype(np.uint8)) and np.allclose(gain, rg) and np.allclose(obs, ro)
    assert np.allclose(gain, p.gain(agc))
    # a burst of strong echoes drives the AGC down, weak ones up (the loop's sign)
    tt = np.linspace(0, 0.05, 200)
    s0 = np.zeros(200, dtype=np.int64)
    strong, _, _ = agc_sequence(tt, np.full(200, 400.0), s0, p, np.random.default_rng(1))
    weak, _, _ = agc_sequence(tt, np.full(200, 20.0), s0, p, np.random.default_rng(1))
    assert strong[100:].mean() < weak[100:].mean() - 5


def test_agc_loop_rejects_unsorted_times():
    p = AGCParams.from_row(load_datasets(["2010_12_1"]).iloc[0])
    with pytest.raises(ValueError, match="non-decreasing"):
        agc_sequence([2.0, 1.0], [10.0, 10.0], [0, 0], p, np.random.default_rng(0))


# -- recording -----------------------------------------------------------------------------

def test_sample_analog_matches_interpolation():
    rng = np.random.default_rng(2)
    a = rng.random((5, 300))
    pos0 = np.array([-10.3, 0.0, 17.25, 250.5, np.nan])
    out = sample_analog(a, pos0, 20.0, 20)
    assert np.allclose(out, sample_reference(a, pos0, 20.0, 20))


def test_plane_record_amplitude_range_and_window(sensor):
    n = 400
    rng = np.random.default_rng(0)
    r = rng.uniform(1150, 1250, n)
    gain = rng.uniform(0.6, 1.4, n)
    sig, t0 = spike_sigma(n), spike_t0(r)
    a0 = unit_gain_peaks(sensor, sig, t0, r)
    assert np.allclose(a0, sensor.system.peak * 0.3 / np.pi / r**2)
    rec = record(sensor, sig, t0, r, gain, np.random.default_rng(1))
    assert np.all(rec.n_echoes == 1)
    # echo amplitude = gain x S peak x sigma / R^2 (Eq. 7); DR intensity within its noise
    assert np.allclose(rec.echo_amp_dn[:, 0], gain * a0, rtol=1e-3)
    assert np.abs(rec.intensity[:, 0] - gain * a0).max() < 0.5 + 5 * sensor.intensity_noise_dn
    # DR range = true range + range walk + timing jitter
    dr = rec.echo_ns[:, 0] * RANGE_PER_NS
    err = dr - r - sensor.range_walk_m(gain * a0)
    assert abs(err.mean()) < 4 * sensor.timing_jitter_ns * RANGE_PER_NS / np.sqrt(n)
    assert err.std() == pytest.approx(sensor.timing_jitter_ns * RANGE_PER_NS, rel=0.15)
    # the record starts 3.3-4.8 m before the first echo and is 256 ns long
    pre = (rec.echo_ns[:, 0] - rec.first_sample_ns) * RANGE_PER_NS
    assert pre.min() >= 3.3 and pre.max() <= 4.8
    assert rec.samples.shape == (n, 256) and rec.samples.dtype == np.uint8
    peak = rec.samples.max(axis=1) - sensor.noise_mean_dn
    assert np.mean(peak / (gain * a0)) == pytest.approx(1.0, abs=0.02)
    tail = rec.samples[:, -50:].astype(float)
    assert tail.mean() == pytest.approx(sensor.noise_mean_dn, abs=0.05)
    assert tail.std() == pytest.approx(np.hypot(sensor.noise_sd_dn, np.sqrt(1 / 12)), rel=0.05)


def test_record_effects_act_as_defined(sensor):
    n = 300
    r = np.full(n, 1200.0)
    sig, t0, g = spike_sigma(n), spike_t0(r), np.ones(n)
    base = record(sensor, sig, t0, r, g, np.random.default_rng(4))
    a = base.echo_amp_dn[0, 0]
    sat = record(sensor, sig, t0, r, g, np.random.default_rng(4), nonlinearity=80.0)
    assert sat.echo_amp_dn[0, 0] == pytest.approx(80.0 * np.tanh(a / 80.0), rel=1e-6)
    lost = record(sensor, sig, t0, r, g, np.random.default_rng(4), trigger_loss=0.25)
    assert lost.echo_amp_dn[0, 0] == pytest.approx(0.75 * a, rel=1e-6)
    ar = record(sensor, sig, t0, r, g, np.random.default_rng(4), noise_autocorr=0.7)
    var = sensor.noise_sd_dn**2
    for rec, phi in ((base, 0.0), (ar, 0.7)):
        dev = rec.samples[:, -60:].astype(float) - sensor.noise_mean_dn
        lag1 = np.sum(dev[:, 1:] * dev[:, :-1]) / np.sum(dev**2)
        # rounding adds white noise of variance 1/12 DN^2
        assert lag1 == pytest.approx(phi * var / (var + 1 / 12), abs=0.03)
    # the effects leave the random streams alone: the same jitter and offsets
    assert np.allclose(ar.first_sample_ns, base.first_sample_ns)


def test_pulse_without_signal_is_not_recorded(sensor):
    rec = record(sensor, np.zeros((2, 50)), np.full(2, 8000.0), np.full(2, 1200.0), np.ones(2),
                 np.random.default_rng(0))
    assert list(rec.n_echoes) == [0, 0] and np.all(np.isnan(rec.first_sample_ns))
