"""The signal model of Eq. 7 (render): analytic planar returns, effects, and the NumPy reference."""

import math

import numpy as np
import pytest
from reference_sensor import ar1_reference, render_reference, trigger_loss_reference

from waveforest.constants import RANGE_PER_NS
from waveforest.sensor import (
    CFDParams,
    analog_waveforms,
    apply_trigger_loss,
    ar1,
    gaussian_system_waveform,
    render,
)
from waveforest.sensor.signal import saturation_levels

H = 0.05
FWHM = 7.2
S_PEAK = 1.5e9  # DN m^2 per unit sigma: a rho = 0.3 plane at 1200 m gives ~100 DN
TRIGGER_TOL_NS = 1e-3
ENERGY_TOL = 5e-3


def planar(n, rho=0.3, j=300, n_bins=800):
    sig = np.zeros((n, n_bins))
    sig[:, j] = rho / math.pi
    return sig


def test_planar_target_eq7():
    """A spike sigma = rho/pi at R: V = S(t - tau) rho / (pi R^2), trigger at the spike's bin centre."""
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    n, R, j = 400, 1200.0, 300
    t0 = np.random.default_rng(0).uniform(7000, 9000, n)
    r = render(planar(n, j=j), t0, R, sw, 10.0, 0.0, 1.0, np.random.default_rng(1), quantise=False)
    assert np.allclose(r.trigger_ns, t0 + (j + 0.5) * H, atol=TRIGGER_TOL_NS)
    pre_m = (r.trigger_ns - r.first_sample_ns) * RANGE_PER_NS
    assert pre_m.min() > 3.3 - RANGE_PER_NS and pre_m.max() <= 4.8 + 1e-9
    assert pre_m.max() - pre_m.min() > 1.2  # spread over the 3.3-4.8 m range
    amp = S_PEAK * 0.3 / math.pi / R**2
    peak = r.samples.max(axis=1) - 10.0
    s = FWHM / (2 * math.sqrt(2 * math.log(2)))
    assert np.all(peak <= amp * (1 + 1e-6)) and np.all(peak >= amp * math.exp(-0.5 * (0.5 / s) ** 2) * (1 - 1e-5))
    # energy: sum of samples * dt = energy(S) * sigma / R^2
    e = (r.samples - 10.0).sum(axis=1) * 1.0
    assert np.allclose(e, sw.energy * 0.3 / math.pi / R**2, rtol=ENERGY_TOL)
    assert r.samples.shape == (n, 256)
    # random sampling phase: the trigger's position within a sample interval is uniform
    frac = np.mod(r.trigger_ns - r.first_sample_ns, 1.0)
    assert np.histogram(frac, bins=4, range=(0, 1))[0].min() > n / 4 * 0.6


def test_quantised_record_and_clipping():
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    r = render(planar(50), 8000.0, 1200.0, sw, 10.0, 1.5, 1.0, np.random.default_rng(2))
    assert np.array_equal(r.samples, np.rint(r.samples)) and r.samples.min() >= 0 and r.samples.max() <= 255
    hot = render(planar(20, rho=1.0), 8000.0, 400.0, sw, 10.0, 1.5, 1.0, np.random.default_rng(3))
    assert np.all(hot.samples.max(axis=1) == 255)  # clipped at the digitiser maximum
    two = render(planar(20), 8000.0, 1200.0, sw, 10.0, 1.5, 2.0, np.random.default_rng(3), record_ns=256.0)
    assert two.samples.shape == (20, 128)


def test_same_seed_same_output():
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    sig = np.abs(np.random.default_rng(0).normal(0, 0.01, (30, 500)))
    a = render(sig, 8000.0, 1000.0, sw, 10.0, 1.5, 1.0, np.random.default_rng(42), noise_autocorr=0.5)
    b = render(sig, 8000.0, 1000.0, sw, 10.0, 1.5, 1.0, np.random.default_rng(42), noise_autocorr=0.5)
    c = render(sig, 8000.0, 1000.0, sw, 10.0, 1.5, 1.0, np.random.default_rng(43), noise_autocorr=0.5)
    assert np.array_equal(a.samples, b.samples) and np.array_equal(a.first_sample_ns, b.first_sample_ns)
    assert not np.array_equal(a.samples, c.samples)


def test_kernel_matches_reference():
    """render (unquantised) equals np.convolve + np.interp + the CFD reference, same random draws."""
    rng = np.random.default_rng(9)
    sw = gaussian_system_waveform(5.0, 4.0e8)
    n, nb = 25, 600
    sig = np.zeros((n, nb))
    for i in range(n):
        k = rng.integers(1, 40)
        sig[i, rng.integers(50, 550, k)] = rng.exponential(0.02, k)
    sig[3] = 0.0  # no signal: no trigger
    t0 = rng.uniform(5000, 9000, n)
    R = rng.uniform(500, 1500, n)
    gain = rng.uniform(0.6, 1.4, n)
    for kw in ({}, {"nonlinearity": 40.0, "noise_autocorr": 0.6}):
        out = render(sig, t0, R, sw, 9.0, 1.2, 0.5, np.random.default_rng(5), gain=gain, quantise=False, **kw)
        cfd = CFDParams().resolved(sw.fwhm_ns)
        ref, first, trig = render_reference(sig, t0, R, sw.t_ns, sw.s, 9.0, 1.2, 0.5, np.random.default_rng(5),
                                            gain=gain, D=cfd.fine_delay(), dead=cfd.fine_dead(), **kw)
        assert np.allclose(out.trigger_ns, trig, atol=1e-6, equal_nan=True)
        assert np.allclose(out.first_sample_ns, first, atol=1e-6, equal_nan=True)
        assert np.allclose(out.samples, ref, atol=2e-4 * np.abs(ref).max())
    assert np.isnan(out.trigger_ns[3]) and np.isnan(out.first_sample_ns[3])


def test_gain_scales_signal_only():
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    sig = planar(10)
    kw = dict(quantise=False)
    a = render(sig, 8000.0, 1200.0, sw, 10.0, 0.0, 1.0, np.random.default_rng(1), **kw)
    b = render(sig, 8000.0, 1200.0, sw, 10.0, 0.0, 1.0, np.random.default_rng(1), gain=np.full(10, 1.7), **kw)
    assert np.allclose(b.samples - 10.0, 1.7 * (a.samples - 10.0), rtol=1e-5, atol=1e-4)
    assert np.allclose(a.trigger_ns, b.trigger_ns)


def test_noise_autocorrelation_effect():
    """noise_autocorr = phi: lag-1 autocorrelation phi, same marginal SD (no-signal records are noise only)."""
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    sig = np.zeros((400, 10))
    for phi in (0.0, 0.7):
        r = render(sig, 8000.0, 1000.0, sw, 10.0, 2.0, 1.0, np.random.default_rng(7), noise_autocorr=phi,
                   quantise=False)
        assert np.isnan(r.trigger_ns).all()
        e = r.samples.astype(np.float64) - 10.0
        lag1 = np.sum(e[:, 1:] * e[:, :-1]) / np.sum(e[:, :-1] ** 2)
        assert lag1 == pytest.approx(phi, abs=0.01)
        assert e.std() == pytest.approx(2.0, rel=0.02)
        assert e.mean() == pytest.approx(0.0, abs=0.02)
    z = np.random.default_rng(1).standard_normal((5, 50))
    assert np.allclose(ar1(z, 0.8), ar1_reference(z, 0.8))


def test_nonlinearity_effect_is_tanh():
    """Saturation level L: a fine-grid peak v becomes L tanh(v / L)."""
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    sig = planar(1)
    lin, _ = analog_waveforms(sig, 8000.0, 1200.0, sw)
    for L in (50.0, 150.0):
        sat, _ = analog_waveforms(sig, 8000.0, 1200.0, sw, nonlinearity=L)
        v = lin.max()
        assert sat.max() == pytest.approx(L * math.tanh(v / L), rel=1e-12)
        assert sat.max() < v
    r = render(sig, 8000.0, 1200.0, sw, 10.0, 0.0, 1.0, np.random.default_rng(0), nonlinearity=50.0, quantise=False)
    assert r.samples.max() - 10.0 < 50.0


def test_saturation_after_the_gain_is_a_level_per_pulse():
    """Saturating the gained signal (the campaign's sensor) and saturating the normalised one at
    L / g (the simulation of an AGC-normalised twin) differ by the factor g alone."""
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    sig = planar(3, rho=0.4)
    g = np.array([0.8, 1.0, 1.25])
    gained, _ = analog_waveforms(sig, 8000.0, 1200.0, sw, gain=g, nonlinearity=150.0)
    normalised, _ = analog_waveforms(sig, 8000.0, 1200.0, sw, nonlinearity=saturation_levels(150.0, g))
    assert np.allclose(gained / g[:, None], normalised, rtol=1e-12, atol=1e-9)
    assert np.array_equal(saturation_levels(150.0, [np.nan, 0.0, 2.0]), [150.0, 150.0, 75.0])
    with pytest.raises(ValueError, match="nonlinearity"):
        analog_waveforms(sig, 8000.0, 1200.0, sw, nonlinearity=np.array([150.0, -1.0, 150.0]))


def test_trigger_loss_effect():
    """trigger_loss = f removes exactly f of sigma, earliest first; the echo's energy drops by f."""
    rng = np.random.default_rng(3)
    sig = np.abs(rng.normal(0, 1, (20, 300))) * (rng.random((20, 300)) < 0.3)
    for f in (0.15, 0.5):
        out = apply_trigger_loss(sig, f)
        assert np.allclose(out.sum(axis=1), (1 - f) * sig.sum(axis=1))
        assert np.allclose(out, trigger_loss_reference(sig, f))
        removed = sig - out
        for i in range(20):  # earliest first: everything before the last touched bin is gone
            touched = np.flatnonzero(removed[i] > 0)
            assert np.allclose(out[i, : touched[-1]], 0.0)
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    full, _ = analog_waveforms(sig, 8000.0, 1000.0, sw)
    lost, _ = analog_waveforms(sig, 8000.0, 1000.0, sw, trigger_loss=0.15)
    assert np.allclose(lost.sum(axis=1), 0.85 * full.sum(axis=1))


def test_input_errors():
    sw = gaussian_system_waveform(FWHM, S_PEAK)
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match=">= 0"):
        render(-planar(2), 0.0, 1000.0, sw, 10.0, 1.0, 1.0, rng)
    with pytest.raises(ValueError, match="bin_ns"):
        render(planar(2), 0.0, 1000.0, sw, 10.0, 1.0, 1.0, rng, bin_ns=0.1)
    with pytest.raises(ValueError, match="range_m"):
        render(planar(2), 0.0, -5.0, sw, 10.0, 1.0, 1.0, rng)
    with pytest.raises(ValueError, match="trigger_loss"):
        render(planar(2), 0.0, 1000.0, sw, 10.0, 1.0, 1.0, rng, trigger_loss=1.0)
    with pytest.raises(ValueError, match="Generator"):
        render(planar(2), 0.0, 1000.0, sw, 10.0, 1.0, 1.0, 42)
    with pytest.raises(ValueError, match="pre_trigger_m"):
        render(planar(2), 0.0, 1000.0, sw, 10.0, 1.0, 1.0, rng, pre_trigger_m=(5.0, 3.0))
