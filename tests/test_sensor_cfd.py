"""Echo detection: the CFD against analytic Gaussian echoes and its NumPy reference (docs/method.md §(f))."""

import math

import numpy as np
import pytest
from reference_sensor import cfd_reference

from waveforest.constants import RANGE_PER_NS
from waveforest.sensor import (
    CFDParams,
    RangeCorrection,
    apply_range_correction,
    detect_echoes,
    fit_range_correction,
    gaussian_cfd_time,
)

FWHM_PER_SD = 2.0 * math.sqrt(2.0 * math.log(2.0))
CFD_CRITERION_M = 0.10  # the paper: |dR| < 0.10 m ...
CFD_CRITERION_FRACTION = 0.95  # ... for more than 95 % of pulses
CFD_BIAS_TOL_M = 0.015  # "no bias": linear upsampling of 1-ns samples costs <= ~1 cm (docstring)
REF_TIME_TOL_NS = 1e-6
REF_AMP_TOL = 1e-4
NOISE_MEAN = 10.0


def gaussian_waveforms(rng, n, fwhm, amp, sd, *, dt=1.0, record_ns=256.0, quantise=True, mu=None):
    """n waveforms with one Gaussian echo each (random centre), noise and 8-bit rounding."""
    s = fwhm / FWHM_PER_SD
    mu = rng.uniform(40.0, 200.0, n) if mu is None else mu
    t = np.arange(int(round(record_ns / dt))) * dt
    x = NOISE_MEAN + amp * np.exp(-0.5 * ((t[None, :] - mu[:, None]) / s) ** 2)
    x = x + sd * rng.standard_normal(x.shape)
    if quantise:
        x = np.clip(np.rint(x), 0, 255)
    return x.astype(np.float32), mu


def test_paper_criterion_on_gaussian_echoes():
    """|dR| < 0.10 m for > 95 % and no bias, across widths, amplitudes and noise levels."""
    rng = np.random.default_rng(20140101)
    within, cells = [], 0
    for fwhm in (4.0, 7.2, 10.1):
        cfd = CFDParams().resolved(fwhm)
        for amp in (30.0, 60.0, 120.0, 200.0):
            for sd in (0.5, 1.0, 2.0):
                x, mu = gaussian_waveforms(rng, 150, fwhm, amp, sd)
                ech = detect_echoes(x, None, 1.0, NOISE_MEAN, sd, cfd)
                assert np.all(ech.n_echoes == 1), (fwhm, amp, sd)
                dr = (ech.times_ns[:, 0] - mu) * RANGE_PER_NS
                assert abs(dr.mean()) < CFD_BIAS_TOL_M, (fwhm, amp, sd, dr.mean())
                within.append(np.abs(dr) < CFD_CRITERION_M)
                cells += 1
    frac = np.concatenate(within).mean()
    assert cells == 36
    assert frac > CFD_CRITERION_FRACTION, frac


def test_amplitude_independent_and_analytic_for_other_widths():
    """Noise-free echoes of any width: the CFD time is the analytic mu + d/2 + s^2 ln f / d."""
    rng = np.random.default_rng(3)
    sys_fwhm = 7.2
    for frac in (0.3, 0.5, 0.8):
        cfd = CFDParams(fraction=frac).resolved(sys_fwhm)
        for fwhm in (5.0, 7.2, 12.0):
            for amp in (15.0, 240.0):
                x, mu = gaussian_waveforms(rng, 40, fwhm, amp, 0.0, dt=0.25, quantise=False)
                ech = detect_echoes(x, None, 0.25, NOISE_MEAN, 1.0, cfd)
                truth = np.array([gaussian_cfd_time(m, fwhm / FWHM_PER_SD, cfd) for m in mu])
                # linear interpolation of 0.25-ns samples: a few mm at most
                assert np.abs(ech.times_ns[:, 0] - truth).max() * RANGE_PER_NS < 0.005, (frac, fwhm, amp)


def test_default_cfd_time_is_the_peak_of_a_system_width_echo():
    cfd = CFDParams().resolved(7.2)
    assert gaussian_cfd_time(50.0, 7.2 / FWHM_PER_SD, cfd) == pytest.approx(50.0, abs=1e-9)


def test_multiple_echoes_and_dead_time():
    fwhm = 5.0
    s = fwhm / FWHM_PER_SD
    cfd = CFDParams().resolved(fwhm)  # dead time = FWHM = 5 ns
    t = np.arange(256, dtype=float)
    centres = np.array([60.0, 75.0, 100.0, 140.0, 180.0])
    x = NOISE_MEAN + sum(80.0 * np.exp(-0.5 * ((t - c) / s) ** 2) for c in centres)
    ech = detect_echoes(x[None, :], None, 1.0, NOISE_MEAN, 1.0, cfd, max_echoes=4)
    assert ech.n_echoes[0] == 4  # capped at max_echoes
    assert np.allclose(ech.times_ns[0], centres[:4], atol=0.05)
    assert np.allclose(ech.amplitudes[0], 80.0, rtol=0.05)
    # two echoes 3 ns apart (< dead time): one echo only
    x2 = NOISE_MEAN + 80.0 * np.exp(-0.5 * ((t - 60.0) / s) ** 2) + 80.0 * np.exp(-0.5 * ((t - 63.0) / s) ** 2)
    ech2 = detect_echoes(x2[None, :], None, 1.0, NOISE_MEAN, 1.0, cfd)
    assert ech2.n_echoes[0] == 1
    # noise only: nothing
    rng = np.random.default_rng(1)
    noise = NOISE_MEAN + rng.standard_normal((50, 256))
    assert detect_echoes(noise, None, 1.0, NOISE_MEAN, 1.0, CFDParams(arming_sd=6.0).resolved(5.0)).n_echoes.sum() == 0


def test_weak_echo_armed_after_its_crossing_is_found_backwards():
    """A broad echo just above the threshold arms after its CFD point: the crossing is still found."""
    cfd = CFDParams().resolved(4.0)
    fwhm = 6.0
    s = fwhm / FWHM_PER_SD
    t = np.arange(256) * 0.25
    amp = 4.2  # arming level 4 (SD 1) is reached 0.80 ns before the peak, the CFD point is 1.25 ns before
    x = NOISE_MEAN + amp * np.exp(-0.5 * ((t - 30.0) / s) ** 2)
    assert gaussian_cfd_time(30.0, s, cfd) < 30.0 - s * math.sqrt(2 * math.log(amp / 4.0))
    ech = detect_echoes(x[None, :], None, 0.25, NOISE_MEAN, 1.0, cfd)
    assert ech.n_echoes[0] == 1
    assert ech.times_ns[0, 0] == pytest.approx(gaussian_cfd_time(30.0, s, cfd), abs=0.01)


@pytest.mark.parametrize("dt", [0.25, 0.5, 1.0, 2.0])
def test_kernel_matches_reference(dt):
    """The Numba CFD and the literal 0.05-ns upsampling reference agree on random waveforms."""
    rng = np.random.default_rng(int(dt * 100))
    n, n_s = 60, int(200 / dt)
    t = np.arange(n_s) * dt
    x = NOISE_MEAN + rng.normal(0, 1.0, (n, n_s))
    for i in range(n):
        for _ in range(rng.integers(0, 4)):
            c, w, a = rng.uniform(10, 190), rng.uniform(1.5, 12), rng.uniform(2, 150)
            x[i] += a * np.exp(-0.5 * ((t - c) / (w / FWHM_PER_SD)) ** 2)
    x = np.clip(np.rint(x), 0, 255).astype(np.float32)
    lengths = rng.integers(0, n_s + 1, n)
    lengths[:3] = (0, 1, 2)
    x[np.arange(n_s)[None, :] >= lengths[:, None]] = np.nan
    for frac, delay, dead, arm in ((0.5, 3.0, 6.0, 4.0), (0.3, 1.5, 2.0, 3.0), (0.8, 5.0, 0.0, 6.0)):
        cfd = CFDParams(frac, delay, arm, dead)
        ech = detect_echoes(x, lengths, dt, NOISE_MEAN, 1.0, cfd, max_echoes=4)
        for i in range(n):
            rt, ra = cfd_reference(x[i], lengths[i], dt, NOISE_MEAN, arm * 1.0, frac, cfd.fine_delay(),
                                   cfd.fine_dead(), 4)
            assert ech.n_echoes[i] == len(rt), (i, frac)
            assert np.allclose(ech.times_ns[i, : len(rt)], rt, atol=REF_TIME_TOL_NS)
            assert np.allclose(ech.amplitudes[i, : len(rt)], ra, atol=REF_AMP_TOL)
            assert np.isnan(ech.times_ns[i, len(rt):]).all()


def test_per_pulse_sampling_and_noise():
    rng = np.random.default_rng(8)
    x1, mu1 = gaussian_waveforms(rng, 5, 7.2, 80.0, 0.0, dt=1.0, quantise=False)
    x2, mu2 = gaussian_waveforms(rng, 5, 7.2, 80.0, 0.0, dt=2.0, record_ns=512.0, quantise=False)
    x = np.full((10, 256), np.nan, dtype=np.float32)
    x[:5] = x1
    x[5:] = x2
    dt = np.r_[np.ones(5), 2 * np.ones(5)]
    ech = detect_echoes(x, np.full(10, 256), dt, NOISE_MEAN, np.linspace(0.5, 2, 10), CFDParams(), fwhm_ns=7.2)
    assert np.abs(ech.times_ns[:, 0] - np.r_[mu1, mu2]).max() * RANGE_PER_NS < 0.05


def test_range_correction_fit_and_apply():
    rng = np.random.default_rng(4)
    a = rng.uniform(10, 200, 4000)
    walk = 0.06 - 0.0004 * a  # a range walk of 6 cm to -2 cm
    d = walk + rng.normal(0, 0.02, a.size)
    corr = fit_range_correction(a, d)
    assert not corr.is_identity and len(corr.apeak) > 1
    resid = d - corr(a)
    assert abs(np.median(resid)) < 0.002
    for lo in (10, 60, 120, 160):  # no trend left within any amplitude band
        m = (a > lo) & (a < lo + 40)
        assert abs(np.median(resid[m])) < 0.008
    # applying to times: t + dR / (c/2)
    t = np.array([[50.0, np.nan]])
    out = apply_range_correction(t, np.array([[100.0, np.nan]]), corr)
    assert out[0, 0] == pytest.approx(50.0 + corr(np.array([100.0]))[0] / RANGE_PER_NS)
    assert np.isnan(out[0, 1])
    # no trend and no offset -> identity; offset only -> constant
    assert fit_range_correction(a, rng.normal(0, 0.02, a.size)).is_identity
    const = fit_range_correction(a, 0.03 + rng.normal(0, 0.02, a.size))
    assert len(const.apeak) == 1 and const.delta_m[0] == pytest.approx(0.03, abs=0.003)
    assert RangeCorrection.from_dict(corr.to_dict()) == corr
    assert fit_range_correction(a[:5], d[:5]).is_identity  # too few pulses


def test_input_errors():
    x = np.zeros((3, 10), dtype=np.float32)
    with pytest.raises(ValueError, match="2-D"):
        detect_echoes(np.zeros(10), None, 1.0, 0.0, 1.0, CFDParams(), fwhm_ns=5.0)
    with pytest.raises(ValueError, match="pulse FWHM"):
        detect_echoes(x, None, 1.0, 0.0, 1.0, CFDParams())
    with pytest.raises(ValueError, match="lengths"):
        detect_echoes(x, np.array([1, 2]), 1.0, 0.0, 1.0, CFDParams(), fwhm_ns=5.0)
    with pytest.raises(ValueError, match="sampling_ns"):
        detect_echoes(x, None, 0.0, 0.0, 1.0, CFDParams(), fwhm_ns=5.0)
    with pytest.raises(ValueError, match="non-finite"):
        detect_echoes(np.full((1, 5), np.nan), None, 1.0, 0.0, 1.0, CFDParams(), fwhm_ns=5.0)
    with pytest.raises(ValueError, match="fraction"):
        CFDParams(fraction=1.5)
