"""CFD tuning against DR ranges (docs/method.md §(f)): a known discriminator recovered from widened echoes."""

import math

import numpy as np
from test_sensor_cfd import FWHM_PER_SD, NOISE_MEAN, gaussian_waveforms

from waveforest.constants import RANGE_PER_NS
from waveforest.sensor import CFDParams
from waveforest.sensor.cfd_tuning import MIN_CLASS_PULSES, WIDTH_EDGES, tune_cfd, width_class

FWHM = 7.2  # system pulse, ns
DR_FRACTION, DR_DELAY = 0.35, 0.5 * FWHM  # the "sensor's" DR discriminator
WALK_M = -0.025  # range walk per unit ln(A / 50 DN), m
NOISE_SD = 1.3
UNBIASED_M = 0.01  # a tuned CFD leaves every width class within this of the DR ranges: the 1-ns linear
# upsampling costs ~1 cm on wide echoes (cfd.py) and one grid step of delay moves echoes of 1.6 FWHM by ~4 cm
RIDGE_TOL = 0.12  # relative tolerance on ln(f) / delay, the width term of a Gaussian's CFD time


def dr_pulses(rng, widths):
    """One Gaussian echo per pulse of FWHM ``widths`` x FWHM; the DR time of a CFD (0.35, FWHM/2) plus walk."""
    x_all, t_all, amps = [], [], []
    for k in widths:
        amp = rng.uniform(25.0, 150.0)
        x, mu = gaussian_waveforms(rng, 1, k * FWHM, amp, NOISE_SD, record_ns=120.0, mu=rng.uniform(40, 60, 1))
        s = k * FWHM / FWHM_PER_SD
        t_dr = mu + DR_DELAY / 2 + s**2 * math.log(DR_FRACTION) / DR_DELAY  # cfd.py: analytic Gaussian CFD time
        t_dr = t_dr + WALK_M * math.log(amp / 50.0) / RANGE_PER_NS
        x_all.append(x[0])
        t_all.append(t_dr[0])
        amps.append(amp)
    return np.array(x_all), np.array(t_all)


def test_tuning_recovers_the_dr_discriminator_from_wide_echoes():
    """Planar-like and widened echoes: the tuned pair lies on the DR's ridge ln f / delay and no
    width class keeps a bias, where the starting pair (0.5, FWHM/2) puts wide and planar echoes 8 cm apart."""
    rng = np.random.default_rng(7)
    widths = np.concatenate([np.full(600, 1.0), rng.uniform(1.15, 1.28, 300), rng.uniform(1.35, 1.9, 300)])
    x, t_dr = dr_pulses(rng, widths)
    width_ns = widths * FWHM
    start = CFDParams(fraction=0.5)
    tuning = tune_cfd(x, None, np.ones(len(x)), t_dr, width_ns, NOISE_MEAN, NOISE_SD, start, FWHM)
    assert tuning.tuned, tuning.reason
    bias = tuning.ranges.class_bias(tuning.classes)
    assert np.all(np.abs(bias) < UNBIASED_M), bias
    ridge = math.log(tuning.cfd.fraction) / tuning.cfd.delay_ns
    truth = math.log(DR_FRACTION) / DR_DELAY
    assert abs(ridge / truth - 1) < RIDGE_TOL, (tuning.cfd, ridge, truth)
    assert tuning.grid["score_m"].min() == np.nanmax(np.abs(bias))

    untuned = tune_cfd(x, None, np.ones(len(x)), t_dr, width_ns, NOISE_MEAN, NOISE_SD, start, FWHM, tune=False)
    assert not untuned.tuned and untuned.cfd.fraction == 0.5 and untuned.grid.empty
    # with the wrong pair no amplitude correction serves all widths: wide and planar echoes 8 cm apart
    off = untuned.ranges.class_bias(untuned.classes)
    assert off[-1] - off[0] < -0.08, off


def test_no_tuning_without_wide_echoes():
    """Planar echoes alone cannot fix (f, delay): the starting pair is kept and the reason given."""
    rng = np.random.default_rng(8)
    x, t_dr = dr_pulses(rng, np.full(300, 1.0))
    tuning = tune_cfd(x, None, np.ones(len(x)), t_dr, np.full(len(x), FWHM), NOISE_MEAN, NOISE_SD,
                      CFDParams(fraction=0.5), FWHM)
    assert not tuning.tuned and tuning.cfd.fraction == 0.5 and tuning.cfd.delay_ns == 0.5 * FWHM
    assert str(MIN_CLASS_PULSES) in tuning.reason


def test_width_classes():
    w = FWHM * np.array([0.9, 1.0, WIDTH_EDGES[0] - 1e-9, WIDTH_EDGES[0] + 1e-9, WIDTH_EDGES[1] + 1e-9, np.nan])
    assert width_class(w, FWHM).tolist() == [0, 0, 0, 1, 2, -1]
