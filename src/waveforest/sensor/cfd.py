"""Echo detection: a constant fraction discriminator on the waveform (docs/method.md §(f)).

The waveform ``x`` (samples minus the noise mean) is upsampled to the 0.05-ns grid by linear
interpolation, ``x_f[m] = x(m * 0.05 ns)``, and the CFD signal is

    y[m] = f * x_f[m] - x_f[m - D]          (D = delay / 0.05 ns; x_f = 0 before the record)

Sign convention: on the leading edge of an echo ``f x(t)`` exceeds the delayed ``x(t - delay)``
so ``y > 0``; it turns negative once the delayed copy catches up. The echo time is that
**+ to - zero crossing**, linearly interpolated between the two fine points. For a Gaussian
echo of SD s it falls at ``mu + delay/2 + s^2 ln(f)/delay`` -- independent of amplitude; with
the defaults (f = 0.5, delay = FWHM/2 of the system pulse) exactly on the peak of a
system-width echo. The system waveform's t = 0 is defined as this CFD time of a planar target
(a spike in sigma), so simulated CFD ranges reproduce the DR ranges without bias.

Arming: the CFD is armed at the first fine point where ``x_f`` exceeds ``arming_sd`` noise
SDs. If ``y`` is already <= 0 there (a weak echo that crosses the threshold after its CFD
point), the crossing is taken as the last + to - crossing within one dead time (at least one
delay) before arming; otherwise the first crossing after arming. The CFD disarms if ``x_f``
falls back to the threshold before a crossing. After an echo the next one is searched from
one dead time later (re-arming on the level, so overlapping echoes are separated when the
second one rises). Up to ``max_echoes`` echoes per pulse.

A crossing counts only if ``y`` stays <= 0 for half a delay after it (after the arming point
for a crossing found backwards): on a strong echo the far tail arms the CFD where ``y`` is
still at noise level, and a noise dip there would otherwise trigger nanoseconds early.

The amplitude of an echo is the maximum of the linear interpolant of ``x`` from one delay
before to one dead time after the crossing.

Known bias of the linear upsampling (noise-free Gaussian echoes of the system width, random
sampling phase; the CFD time comes early): 0.5 cm at FWHM 7.2 ns and 1-ns sampling (0.9 cm
at FWHM 4 ns), 2 cm at 2-ns sampling, 6-17 cm at 4-ns sampling. Real and simulated
waveforms share it, and the range correction fitted against DR ranges absorbs it.

Working on the piecewise-linear interpolant directly is exactly the 0.05-ns upsampling of
the method, without storing the 20x longer upsampled waveform.

Range correction (docs/method.md §(f)): ``dR(Apeak) = DR range - own CFD range`` fitted on pulses
where DR ranges exist (:func:`fit_range_correction`), a binned table with linear
interpolation between bin medians, a constant, or the identity when there is neither a trend
nor an offset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit, prange

import waveforest.sensor.checks as checks
from waveforest.constants import RANGE_PER_NS
from waveforest.sensor.params import CFD_PERSIST_FRACTION, FINE_EPS, FINE_NS, RANGE_TREND_Z, CFDParams


@njit(cache=True)
def _xf(row, n, mean, inv_dt, t):
    """Linear interpolant of ``row[:n] - mean`` at ``t`` ns from the first sample (0 before it)."""
    if t < 0.0:
        return 0.0
    u = t * inv_dt
    k = int(u)
    if k >= n - 1:
        return row[n - 1] - mean
    w = u - k
    return (1.0 - w) * (row[k] - mean) + w * (row[k + 1] - mean)


@njit(cache=True)
def _y(row, n, mean, inv_dt, frac, D, m):
    """CFD signal at fine index ``m``."""
    return frac * _xf(row, n, mean, inv_dt, m * FINE_NS) - _xf(row, n, mean, inv_dt, (m - D) * FINE_NS)


@njit(cache=True)
def _next_armed(row, n, mean, inv_dt, dt, thr, m, M):
    """First fine index >= m where the interpolant exceeds ``thr`` (-1 if none).

    Fine points are only visited in sample intervals whose right end exceeds the threshold
    (a linear piece exceeds a level only if one of its ends does); the rest is a coarse scan.
    """
    while m < M:
        t = m * FINE_NS
        if _xf(row, n, mean, inv_dt, t) > thr:
            return m
        k = int(t * inv_dt)
        if k + 1 < n and row[k + 1] - mean > thr:
            m += 1
            continue
        kk = k + 2
        while kk < n and row[kk] - mean <= thr:
            kk += 1
        if kk >= n:
            return -1
        m_new = int(math.floor((kk - 1) * dt / FINE_NS + FINE_EPS)) + 1
        m = max(m + 1, m_new)
    return -1


@njit(cache=True)
def _first_positive(row, n, mean, inv_dt, frac, D, start, Q, M):
    """First fine index in [start, start + Q) where the CFD signal is > 0 (-1 if none)."""
    for q in range(start, min(start + Q, M)):
        if _y(row, n, mean, inv_dt, frac, D, q) > 0.0:
            return q
    return -1


@njit(cache=True)
def _max_interp(row, n, mean, inv_dt, dt, t_lo, t_hi):
    """Maximum of the linear interpolant of ``row[:n] - mean`` over [t_lo, t_hi]."""
    best = max(_xf(row, n, mean, inv_dt, t_lo), _xf(row, n, mean, inv_dt, t_hi))
    k0 = max(0, int(math.ceil(t_lo * inv_dt)))
    k1 = min(n - 1, int(math.floor(t_hi * inv_dt)))
    for k in range(k0, k1 + 1):
        v = row[k] - mean
        if v > best:
            best = v
    return best


@njit(cache=True)
def cfd_row(row, n, dt, mean, thr, frac, D, dead, max_echoes, out_t, out_a):
    """CFD echoes of one waveform; writes times (ns from the first sample) and amplitudes.

    Parameters
    ----------
    row : (n_s,) float array, DN; only ``row[:n]`` is read.
    n : int, valid samples.  dt : float, sampling interval, ns.
    mean : float, noise mean, DN.  thr : float, arming level above the mean, DN.
    frac : float, CFD fraction.  D : int, delay in fine steps.  dead : int, dead time in fine steps.
    max_echoes : int.  out_t, out_a : (>= max_echoes,) float64 outputs.

    Returns
    -------
    int : number of echoes written.
    """
    if n < 2:
        return 0
    inv_dt = 1.0 / dt
    M = int(math.floor((n - 1) * dt / FINE_NS + FINE_EPS)) + 1
    lookback = max(dead, D)
    Q = max(1, int(round(CFD_PERSIST_FRACTION * D)))
    ne = 0
    m = 0
    m_lo = 0
    while ne < max_echoes and m < M:
        m_a = _next_armed(row, n, mean, inv_dt, dt, thr, m, M)
        if m_a < 0:
            break
        j = -1
        y_a = _y(row, n, mean, inv_dt, frac, D, m_a)
        if y_a <= 0.0:  # armed after the crossing: the last + -> - crossing shortly before
            lo = max(m_lo, m_a - lookback)
            k = m_a - 1
            while k >= lo:
                if _y(row, n, mean, inv_dt, frac, D, k) > 0.0:
                    if _first_positive(row, n, mean, inv_dt, frac, D, k + 1, m_a - k + Q, M) < 0:
                        j = k
                    break
                k -= 1
        if j < 0:  # the first lasting + -> - crossing after arming, unless the signal falls back first
            yp = y_a
            mm = m_a + 1
            while mm < M:
                yc = _y(row, n, mean, inv_dt, frac, D, mm)
                if yp > 0.0 and yc <= 0.0:
                    p = _first_positive(row, n, mean, inv_dt, frac, D, mm, Q, M)
                    if p < 0:
                        j = mm - 1
                        break
                    yp = _y(row, n, mean, inv_dt, frac, D, p)
                    mm = p + 1
                    continue
                if _xf(row, n, mean, inv_dt, mm * FINE_NS) <= thr:
                    break
                yp = yc
                mm += 1
            if j < 0:
                m = mm + 1
                continue
        y0 = _y(row, n, mean, inv_dt, frac, D, j)
        y1 = _y(row, n, mean, inv_dt, frac, D, j + 1)
        out_t[ne] = (j + y0 / (y0 - y1)) * FINE_NS
        lo_w = max(0, j - D) * FINE_NS
        hi_w = min(M - 1, j + 1 + dead) * FINE_NS
        out_a[ne] = _max_interp(row, n, mean, inv_dt, dt, lo_w, hi_w)
        ne += 1
        m_lo = j + 1 + dead
        m = m_lo
    return ne


@njit(parallel=True, cache=True, nogil=True)
def cfd_kernel(samples, lengths, dt, mean, thr, frac, D, dead, max_echoes, out_t, out_a, out_n):
    """CFD over a table of waveforms (prange over pulses); outputs pre-filled by the caller."""
    for i in prange(samples.shape[0]):
        out_n[i] = cfd_row(samples[i], lengths[i], dt[i], mean[i], thr[i], frac, D, dead,
                            max_echoes, out_t[i], out_a[i])


class Echoes(NamedTuple):
    """CFD echoes of a table of waveforms (unpacks as ``times_ns, amplitudes, n_echoes``).

    times_ns : (n, max_echoes) float64, ns from the first sample, NaN-padded.
    amplitudes : (n, max_echoes) float64, DN above the noise mean, NaN-padded.
    n_echoes : (n,) int16.
    """

    times_ns: np.ndarray
    amplitudes: np.ndarray
    n_echoes: np.ndarray


def detect_echoes(samples, lengths, sampling_ns, noise_mean, noise_sd, cfd: CFDParams | None = None,
                  max_echoes: int = 4, *, fwhm_ns: float | None = None,
                  range_correction: RangeCorrection | None = None) -> Echoes:
    """Echoes of every waveform by the constant fraction discriminator (docs/method.md §(f)).

    Parameters
    ----------
    samples : (n, n_s) array, DN; NaN padding beyond ``lengths`` is ignored.
    lengths : (n,) int or None (= all samples valid).
    sampling_ns : float or (n,) float, sampling interval, ns.
    noise_mean, noise_sd : float or (n,) float, DN (arming level = mean + arming_sd * sd).
    cfd : CFDParams; delay/dead time None are filled from ``fwhm_ns`` (the system pulse FWHM).
    max_echoes : int, most echoes per pulse (ALS60: 4).
    fwhm_ns : float, optional; system pulse FWHM, needed when ``cfd`` is not resolved.
    range_correction : RangeCorrection, optional; applied to the times (amplitude-dependent).

    Returns
    -------
    Echoes (times_ns, amplitudes, n_echoes); times count from the first sample.
    """
    cfd = (cfd or CFDParams()).resolved(fwhm_ns)
    x, lens = checks.waveforms(samples, lengths)
    n = x.shape[0]
    if int(max_echoes) < 1:
        raise ValueError(f"max_echoes must be >= 1, got {max_echoes}")
    max_echoes = int(max_echoes)
    dt = checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    mean = checks.per_pulse(noise_mean, n, "noise_mean")
    sd = checks.per_pulse(noise_sd, n, "noise_sd", nonnegative=True)
    thr = cfd.arming_sd * sd
    times = np.full((n, max_echoes), np.nan)
    amps = np.full((n, max_echoes), np.nan)
    counts = np.zeros(n, dtype=np.int64)
    if n:
        cfd_kernel(x, lens, dt, mean, thr, float(cfd.fraction), cfd.fine_delay(), cfd.fine_dead(),
                    max_echoes, times, amps, counts)
    if range_correction is not None:
        times = range_correction.apply(times, amps)
    return Echoes(times, amps, counts.astype(np.int16))


def gaussian_cfd_time(mu_ns: float, sd_ns: float, cfd: CFDParams) -> float:
    """Analytic CFD time of a Gaussian echo ``exp(-(t - mu)^2 / (2 sd^2))`` (continuous time).

    ``t_c = mu + delay/2 + sd^2 ln(fraction) / delay`` -- the truth of the CFD tests.
    """
    if cfd.delay_ns is None:
        raise ValueError("cfd.delay_ns is None: resolve the CFD parameters first")
    d = cfd.fine_delay() * FINE_NS
    return float(mu_ns + d / 2.0 + sd_ns**2 * math.log(cfd.fraction) / d)


@dataclass(frozen=True)
class RangeCorrection:
    """Amplitude-dependent range correction dR(Apeak), m, added to CFD ranges (docs/method.md §(f)).

    ``apeak`` are the nodes (bin medians of the peak amplitude, DN) and ``delta_m`` the
    correction there (bin medians of DR range - CFD range); linear interpolation between
    nodes and constant beyond them. No node = identity; one node = a constant offset.
    """

    apeak: tuple[float, ...] = ()
    delta_m: tuple[float, ...] = ()

    def __post_init__(self):
        if len(self.apeak) != len(self.delta_m):
            raise ValueError("RangeCorrection: apeak and delta_m differ in length")
        if len(self.apeak) > 1 and np.any(np.diff(self.apeak) <= 0):
            raise ValueError("RangeCorrection: apeak nodes must increase")

    @classmethod
    def identity(cls) -> RangeCorrection:
        return cls()

    @property
    def is_identity(self) -> bool:
        return len(self.apeak) == 0

    def __call__(self, apeak) -> np.ndarray:
        """dR, m, at the given amplitudes (NaN where the amplitude is NaN)."""
        a = np.asarray(apeak, dtype=np.float64)
        if self.is_identity:
            out = np.zeros_like(a)
        elif len(self.apeak) == 1:
            out = np.full_like(a, self.delta_m[0])
        else:
            out = np.interp(a, np.asarray(self.apeak), np.asarray(self.delta_m))
        return np.where(np.isnan(a), np.nan, out)

    def apply(self, times_ns, amplitudes) -> np.ndarray:
        """Echo times corrected by dR(amplitude): t + dR / RANGE_PER_NS (NaN stays NaN)."""
        t = np.asarray(times_ns, dtype=np.float64)
        if self.is_identity:
            return t.copy()
        d = self(amplitudes)
        return t + np.where(np.isnan(t), np.nan, d) / RANGE_PER_NS

    def to_dict(self) -> dict:
        return {"apeak": [float(v) for v in self.apeak], "delta_m": [float(v) for v in self.delta_m]}

    @classmethod
    def from_dict(cls, d: dict | None) -> RangeCorrection:
        if not d:
            return cls()
        return cls(tuple(float(v) for v in d.get("apeak", ())), tuple(float(v) for v in d.get("delta_m", ())))


def _median_se(v: np.ndarray) -> float:
    """Standard error of the median of a normal-ish sample (sqrt(pi/2) * SD / sqrt(n))."""
    if len(v) < 2:
        return np.inf
    return float(math.sqrt(math.pi / 2.0) * np.std(v, ddof=1) / math.sqrt(len(v)))


def fit_range_correction(apeak, dr_minus_cfd_m, *, n_bins: int = 8, min_per_bin: int = 20) -> RangeCorrection:
    """Fit dR(Apeak) = DR range - own CFD range as a binned table (docs/method.md §(f)).

    Bins hold equal numbers of pulses (amplitude quantiles); the node of a bin is its median
    amplitude and its value the median dR. The table is kept only if some bin differs from
    the pooled median by more than :data:`RANGE_TREND_Z` standard errors; otherwise a
    constant (the pooled median) if that differs from zero by as much, else the identity.

    Parameters
    ----------
    apeak : (n,) float, DN.  dr_minus_cfd_m : (n,) float, m.  Non-finite pairs are ignored.
    n_bins : int, most bins.  min_per_bin : int, fewest pulses per bin.
    """
    a = np.asarray(apeak, dtype=np.float64).ravel()
    d = np.asarray(dr_minus_cfd_m, dtype=np.float64).ravel()
    if a.shape != d.shape:
        raise ValueError("apeak and dr_minus_cfd_m must have the same length")
    ok = np.isfinite(a) & np.isfinite(d)
    a, d = a[ok], d[ok]
    if len(a) < max(min_per_bin, 2):
        return RangeCorrection.identity()
    pooled, se_pooled = float(np.median(d)), _median_se(d)
    k = int(min(n_bins, len(a) // min_per_bin))
    if k >= 2:
        order = np.argsort(a, kind="stable")
        groups = np.array_split(order, k)
        nodes = np.array([np.median(a[g]) for g in groups])
        meds = np.array([np.median(d[g]) for g in groups])
        ses = np.array([_median_se(d[g]) for g in groups])
        z = np.abs(meds - pooled) / np.sqrt(ses**2 + se_pooled**2)
        if np.any(z > RANGE_TREND_Z) and np.all(np.diff(nodes) > 0):
            return RangeCorrection(tuple(nodes.tolist()), tuple(meds.tolist()))
    if abs(pooled) > RANGE_TREND_Z * se_pooled:
        return RangeCorrection((float(np.median(a)),), (pooled,))
    return RangeCorrection.identity()


def apply_range_correction(times_ns, amplitudes, correction: RangeCorrection) -> np.ndarray:
    """Echo times (ns) corrected by an amplitude-dependent range correction."""
    return correction.apply(times_ns, amplitudes)
