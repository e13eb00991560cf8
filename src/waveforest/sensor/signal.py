"""The signal model of Eq. 7: from sigma(t) to a recorded ALS60-like waveform (docs/method.md §(c)).

For each pulse, on the 0.05-ns grid:

1. ``trigger_loss`` effect: the fraction f of sigma(t) is removed earliest first (cumulative,
   the bin that straddles the cut is scaled) -- energy intercepted before the trigger.
2. Eq. 7 as a discrete convolution of per-bin sums (docs/method.md §(c), note 1):
   ``V[k] = gain * sum_j S[k - j] sigma[j] / R^2``. sigma bin j (left edge ``t0 + j h``) is
   placed at its centre ``t0 + (j + 1/2) h``, so V[k] lies at ``t0 + t_S[0] + (k + 1/2) h``.
   ``gain`` is an optional per-pulse factor of the signal (the virtual campaign's AGC).
3. ``nonlinearity`` effect: detector saturation ``v -> L tanh(v / L)`` (L in DN; 0 = linear),
   one level for all pulses or one per pulse: the saturation acts on the signal after the
   receiver's AGC gain, so a pulse rendered in AGC-normalised DN (no ``gain``) with AGC gain g
   saturates at L / g.
4. Trigger: the first CFD echo (:mod:`waveforest.sensor.cfd`) of this noise-free fine-grid
   signal, armed at ``arming_sd * noise_sd`` -- the DR circuit seeing the analog signal. The
   virtual campaign may trigger differently (its own CFD with range walk).
5. Record window: ``record_ns`` long, starting a uniform ``pre_trigger_m`` (3.3-4.8 m of
   range, i.e. / RANGE_PER_NS ns of two-way time) before the trigger, on a free-running
   digitiser clock of random phase: samples at ``phi + i dt`` (phi uniform in [0, dt)), the
   first tick not before ``trigger - pre``. Point sampling of the fine signal (linear).
6. Noise at the output rate (docs/method.md §(c), note 3): Gaussian, dataset mean and SD; with the
   ``noise_autocorr`` effect a stationary AR(1) of the same SD.
7. Rounding to integer DN and clipping to [0, digitizer_max] (``quantise=True``).

A pulse whose signal never arms the CFD (e.g. sigma = 0) has no trigger: its trigger and
first-sample times are NaN and its record is noise only; callers drop such pulses (the ALS60
stores no waveform without a DR echo).

Implementation: pulses in blocks of ``_CHUNK``; per block one Numba kernel for steps 2-3, the
CFD kernel of :mod:`waveforest.sensor.cfd` for step 4 and one kernel for step 5, each called
from Python (a cached Numba kernel must not call a kernel of another module: Numba's cache
would not notice when that module changes).

Random draws, in this order from the caller's Generator: pre-trigger distances (n,), clock
phases (n,), standard normal noise (n, n_s). Same seed -> identical output.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

import waveforest.sensor.checks as checks
from waveforest.constants import RANGE_PER_NS, RECORD_NS
from waveforest.sensor.cfd import cfd_kernel
from waveforest.sensor.noise import gaussian_noise
from waveforest.sensor.params import FINE_NS, CFDParams
from waveforest.sensor.system_waveform import SystemWaveform

_CHUNK = 1024
"""Pulses per block of fine-grid signals in :func:`render` (~1024 x a few thousand float64)."""


class Rendered(NamedTuple):
    """Rendered waveforms.

    samples : (n, n_s) float32, DN (rounded and clipped if ``quantise``).
    first_sample_ns : (n,) float64, two-way time from emission of sample 0, ns (NaN: no trigger).
    trigger_ns : (n,) float64, two-way time from emission of the trigger (first CFD echo of
        the noise-free signal), ns (NaN: no trigger).
    signal : (n, n_s) float32, the noise-free sampled signal above the noise mean, DN.
    sampling_ns : float, sampling interval, ns.
    """

    samples: np.ndarray
    first_sample_ns: np.ndarray
    trigger_ns: np.ndarray
    signal: np.ndarray
    sampling_ns: float


def apply_trigger_loss(sigma: np.ndarray, fraction: float) -> np.ndarray:
    """sigma with the fraction ``fraction`` of each row's total removed earliest first.

    Parameters
    ----------
    sigma : (n, n_bins) float, non-negative per-bin sums.
    fraction : float in [0, 1).

    Returns
    -------
    (n, n_bins) float64; each row sums to (1 - fraction) of its original total.
    """
    sigma = np.asarray(sigma, dtype=np.float64)
    if not (0.0 <= fraction < 1.0):
        raise ValueError(f"trigger_loss must lie in [0, 1), got {fraction}")
    if fraction == 0.0:
        return sigma.copy()
    csum = np.cumsum(sigma, axis=1)
    before = csum - sigma
    cut = fraction * csum[:, -1:]
    removed = np.clip(cut - before, 0.0, sigma)
    return sigma - removed


@njit(cache=True)
def _convolve_into(sig, w, S, out):
    """out[j + k] += w * sigma[j] * S[k] for every non-zero sigma bin (out pre-zeroed)."""
    ns = S.shape[0]
    for j in range(sig.shape[0]):
        sj = sig[j]
        if sj != 0.0:
            a = w * sj
            for k in range(ns):
                out[j + k] += a * S[k]


@njit(cache=True)
def _saturate(v, level):
    if level > 0.0:
        for k in range(v.shape[0]):
            v[k] = level * math.tanh(v[k] / level)


@njit(parallel=True, cache=True, nogil=True)
def _analog_kernel(sigma, w, S, level, out):
    """Fine-grid signal of every pulse: (n, n_bins + n_S - 1) into ``out`` (pre-zeroed);
    ``level``: (n,) saturation level per pulse (0 = linear)."""
    for i in prange(sigma.shape[0]):
        _convolve_into(sigma[i], w[i], S, out[i])
        _saturate(out[i], level[i])


@njit(cache=True)
def _lerp_into(v, p, u, out, k):
    """out[p, k] = row p of ``v`` (n, m) linearly interpolated at fractional index u; unchanged
    outside [0, m - 1]."""
    m = v.shape[1]
    if u < 0.0 or u > m - 1:
        return
    i = int(u)
    if i >= m - 1:
        out[p, k] = v[p, m - 1]
    else:
        f = u - i
        out[p, k] = (1.0 - f) * v[p, i] + f * v[p, i + 1]


@njit(parallel=True, cache=True, nogil=True)
def _sample_kernel(v, tv0, trig_rel, pre_ns, phase_ns, dt, out, trig, first):
    """Record window and point sampling of fine-grid signals (prange over pulses).

    Parameters
    ----------
    v : (n, nv) float64 fine-grid signals.  tv0 : (n,) time of v[:, 0] from emission, ns.
    trig_rel : (n,) first CFD echo of v, ns from v[:, 0] (NaN: no trigger).
    pre_ns : (n,) pre-trigger time, ns.  phase_ns : (n,) digitiser clock phase, ns.
    dt : sampling interval, ns.  out : (n, n_s) float64 (pre-zeroed).  trig, first : (n,) outputs.
    """
    n, nv = v.shape
    n_s = out.shape[1]
    for i in prange(n):
        if not math.isfinite(trig_rel[i]):
            trig[i] = np.nan
            first[i] = np.nan
            continue
        t_trig = tv0[i] + trig_rel[i]
        trig[i] = t_trig
        start = t_trig - pre_ns[i]
        ts = phase_ns[i] + math.ceil((start - phase_ns[i]) / dt) * dt
        first[i] = ts
        for k in range(n_s):
            _lerp_into(v, i, (ts + k * dt - tv0[i]) / FINE_NS, out, k)


@njit(cache=True, nogil=True, parallel=True)
def _grid_sample_kernel(analog, pos0, step, out):
    """out[p, k] = analog[p] linearly interpolated at fractional index pos0[p] + k step (0 outside)."""
    n = analog.shape[0]
    n_s = out.shape[1]
    for p in prange(n):
        if not np.isfinite(pos0[p]):
            continue
        for k in range(n_s):
            _lerp_into(analog, p, pos0[p] + k * step, out, k)


def sample_analog(analog, pos0, step: float, n_samples: int) -> np.ndarray:
    """Point samples of fine-grid signals.

    Parameters
    ----------
    analog : (n, m) float64
        Signals on a uniform grid (index units).
    pos0 : (n,) float64
        Fractional grid index of sample 0 (NaN: leave the row zero).
    step : float
        Sample spacing in grid units (> 0).
    n_samples : int

    Returns
    -------
    (n, n_samples) float64, zero outside the signal.
    """
    a = np.ascontiguousarray(analog, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"analog: expected shape (n, m), got {a.shape}")
    p = np.ascontiguousarray(pos0, dtype=np.float64)
    if p.shape != (a.shape[0],):
        raise ValueError(f"pos0: expected shape ({a.shape[0]},), got {p.shape}")
    if not step > 0 or n_samples < 0:
        raise ValueError("step must be > 0 and n_samples >= 0")
    out = np.zeros((a.shape[0], int(n_samples)))
    if a.shape[0] and a.shape[1] and n_samples:
        _grid_sample_kernel(a, p, float(step), out)
    return out


def _check_sigma(sigma, t0_ns, range_m, gain):
    sig = np.asarray(sigma, dtype=np.float64)
    if sig.ndim != 2:
        raise ValueError(f"sigma must be 2-D (n_pulses, n_bins), got shape {sig.shape}")
    if not np.isfinite(sig).all():
        raise ValueError("sigma must be finite")
    if (sig < 0).any():
        raise ValueError("sigma must be >= 0 (per-bin sums of non-negative contributions)")
    n = sig.shape[0]
    t0 = checks.per_pulse(t0_ns, n, "t0_ns")
    r = checks.per_pulse(range_m, n, "range_m", positive=True)
    g = np.ones(n) if gain is None else checks.per_pulse(gain, n, "gain", positive=True)
    return np.ascontiguousarray(sig), t0, r, g


def saturation_levels(level: float, gain) -> np.ndarray:
    """Saturation levels L / g of pulses with AGC gains g in AGC-normalised DN (g not finite
    or <= 0, e.g. no AGC: 1)."""
    return float(level) / checks.gain_or_one(gain)


def _check_effects(noise_autocorr, nonlinearity, trigger_loss, n: int) -> np.ndarray:
    """Check the sensor effects; return the (n,) saturation levels."""
    if not (-1.0 < noise_autocorr < 1.0):
        raise ValueError(f"noise_autocorr must lie in (-1, 1), got {noise_autocorr}")
    if not (0.0 <= trigger_loss < 1.0):
        raise ValueError(f"trigger_loss must lie in [0, 1), got {trigger_loss}")
    return checks.per_pulse(nonlinearity, n, "nonlinearity (saturation level, DN)", nonnegative=True)


def analog_waveforms(sigma, t0_ns, range_m, system: SystemWaveform, *, gain=None, nonlinearity=0.0,
                     trigger_loss: float = 0.0, bin_ns: float = FINE_NS) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free fine-grid signals of Eq. 7 (steps 1-3 of the module docstring).

    Parameters
    ----------
    sigma : (n, n_bins) float, per-bin sums on the 0.05-ns grid; bin 0's left edge at ``t0_ns``.
    t0_ns : (n,) float, two-way time from emission, ns.  range_m : float or (n,), R of Eq. 7, m.
    system : SystemWaveform.  gain : (n,) float or None.  nonlinearity : float or (n,), DN.
    trigger_loss : effect.

    Returns
    -------
    v : (n, n_bins + len(S) - 1) float64, DN above the noise mean.
    t_first_ns : (n,) float64, two-way time of ``v[:, 0]`` from emission, ns; ``v[:, k]`` is at
        ``t_first_ns + k * 0.05``.
    """
    if abs(bin_ns - FINE_NS) > 1e-9:
        raise ValueError(f"sigma must be binned at {FINE_NS} ns (the S(t) grid), got bin_ns = {bin_ns}")
    sig, t0, r, g = _check_sigma(sigma, t0_ns, range_m, gain)
    level = _check_effects(0.0, nonlinearity, trigger_loss, sig.shape[0])
    if trigger_loss:
        sig = apply_trigger_loss(sig, trigger_loss)
    n, nb = sig.shape
    out = np.zeros((n, nb + system.s.size - 1))
    if n:
        _analog_kernel(sig, g / r**2, system.s, level, out)
    return out, t0 + system.t_ns[0] + 0.5 * FINE_NS


def render(sigma, t0_ns, range_m, system: SystemWaveform, noise_mean, noise_sd, sampling_ns: float,
           rng: np.random.Generator, *, record_ns: float = RECORD_NS, pre_trigger_m=(3.3, 4.8),
           digitizer_max: int = 255, cfd: CFDParams | None = None, noise_autocorr: float = 0.0,
           nonlinearity=0.0, trigger_loss: float = 0.0, gain=None, quantise: bool = True,
           bin_ns: float = FINE_NS) -> Rendered:
    """Recorded waveforms of pulses with cross-section profiles sigma(t) (Eq. 7, docs/method.md §(c)).

    Parameters
    ----------
    sigma : (n, n_bins) float, per-bin sums of sigma per unit emitted power on the 0.05-ns
        grid (the MCRT output); bin 0's left edge at ``t0_ns``.
    t0_ns : (n,) float, two-way time from emission of bin 0's left edge, ns.
    range_m : float or (n,) float, R of Eq. 7, m (suggestion: range to the scene ground point).
    system : SystemWaveform, S(t), DN m^2 per unit sigma.
    noise_mean, noise_sd : float or (n,) float, DN (analog SD: rounding adds its own 1/12 DN^2).
    sampling_ns : float, output sampling interval, ns (0.25-4).
    rng : numpy Generator (see the module docstring for the draw order).
    record_ns : float, record length, ns; n_s = round(record_ns / sampling_ns).
    pre_trigger_m : (lo, hi) m, the record starts uniform(lo, hi) m of range before the trigger.
    digitizer_max : int, largest DN.  cfd : CFDParams of the trigger (unresolved parts from S's FWHM).
    noise_autocorr, nonlinearity, trigger_loss : effects (src/waveforest/effects.py); off = 0;
        nonlinearity a scalar or one saturation level per pulse (step 3), DN.
    gain : (n,) float or None, per-pulse factor on the signal (not the noise).
    quantise : bool, round and clip (False: the analog record, for tests).

    Returns
    -------
    Rendered
    """
    if abs(bin_ns - FINE_NS) > 1e-9:
        raise ValueError(f"sigma must be binned at {FINE_NS} ns (the S(t) grid), got bin_ns = {bin_ns}")
    if not isinstance(system, SystemWaveform):
        raise ValueError("system must be a SystemWaveform")
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator (seeded)")
    sig, t0, r, g = _check_sigma(sigma, t0_ns, range_m, gain)
    n = sig.shape[0]
    level = _check_effects(noise_autocorr, nonlinearity, trigger_loss, n)
    if not (np.isfinite(sampling_ns) and sampling_ns > 0):
        raise ValueError(f"sampling_ns must be > 0, got {sampling_ns}")
    if not (np.isfinite(record_ns) and record_ns >= sampling_ns):
        raise ValueError(f"record_ns must be >= sampling_ns, got {record_ns}")
    lo, hi = (float(v) for v in pre_trigger_m)
    if not (0.0 <= lo <= hi):
        raise ValueError(f"pre_trigger_m must be (lo, hi) with 0 <= lo <= hi, got {pre_trigger_m}")
    if not digitizer_max > 0:
        raise ValueError(f"digitizer_max must be > 0, got {digitizer_max}")
    mean = checks.per_pulse(noise_mean, n, "noise_mean")
    sd = checks.per_pulse(noise_sd, n, "noise_sd", nonnegative=True)
    cfd = (cfd or CFDParams()).resolved(system.fwhm_ns)
    n_s = int(round(record_ns / sampling_ns))

    pre_ns = rng.uniform(lo, hi, n) / RANGE_PER_NS
    phase_ns = rng.random(n) * sampling_ns
    noise = gaussian_noise(rng, (n, n_s), mean, sd, noise_autocorr)

    if trigger_loss:
        sig = apply_trigger_loss(sig, trigger_loss)
    signal = np.zeros((n, n_s))
    trig = np.full(n, np.nan)
    first = np.full(n, np.nan)
    thr = cfd.arming_sd * sd
    nv = sig.shape[1] + system.s.size - 1
    tv0 = t0 + system.t_ns[0] + 0.5 * FINE_NS
    for lo in range(0, n, _CHUNK):  # blocks of pulses bound the fine-grid memory
        sl = slice(lo, min(lo + _CHUNK, n))
        m = sl.stop - sl.start
        v = np.zeros((m, nv))
        _analog_kernel(sig[sl], (g / r**2)[sl], system.s, level[sl], v)
        t_rel = np.full((m, 1), np.nan)
        a_rel = np.full((m, 1), np.nan)
        cfd_kernel(v, np.full(m, nv, dtype=np.int64), np.full(m, FINE_NS), np.zeros(m), thr[sl],
                    float(cfd.fraction), cfd.fine_delay(), cfd.fine_dead(), 1, t_rel, a_rel, np.zeros(m, dtype=np.int64))
        _sample_kernel(v, tv0[sl], t_rel[:, 0], pre_ns[sl], phase_ns[sl], float(sampling_ns), signal[sl], trig[sl],
                       first[sl])
    samples = signal + noise
    if quantise:
        samples = np.clip(np.rint(samples), 0, digitizer_max)
    return Rendered(samples.astype(np.float32), first, trig, signal.astype(np.float32), float(sampling_ns))
