"""The ALS60's own discrete-return (DR) discriminator, as the virtual sensor runs it.

The real ALS60 finds its DR echoes with a constant fraction discriminator (CFD) in separate
fast circuits that see the analog detector signal (docs/method.md §(f)). The virtual sensor runs its
CFD on the noise-free analog signal on the 0.05-ns grid (the timing noise of the real
circuits is added afterwards as a jitter, and the amplitude-dependent range walk as a
function of the echo amplitude, see :mod:`.truth_sensor`). Its parameters (fraction, delay,
arming level, dead time) are the *sensor's*, not the analysis model's: they live in
``resources/campaign/sensor_truth.csv``.

Discriminator (per pulse, on x(t) = analog signal above the baseline, DN):

* y(t) = x(t - delta) - f x(t): negative on a rising edge, it crosses zero from - to +
  at a point of the echo that does not depend on its amplitude;
* the discriminator arms when x >= ``arm_dn``; the echo time is the first - to + zero
  crossing of y in [arming - delta, arming + search) (linear interpolation between bins),
  never before the end of the dead time of the previous echo;
* the echo amplitude is the largest x in [crossing - pre, crossing + post];
* at most ``max_echoes`` (4 for the ALS60, docs/method.md §(a)) echoes per pulse.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from waveforest.constants import BIN_NS

ZERO_DN = 1e-9
"""Analog values below this magnitude (DN) are treated as exactly zero (FFT round-off)."""

SEARCH_FWHM = 2.0
"""The zero crossing is searched up to this many pulse FWHMs after the arming point."""

AMP_PRE_FWHM, AMP_POST_FWHM = 0.5, 1.0
"""The echo amplitude is the maximum within this window around the crossing, in FWHMs."""


@njit(cache=True, inline="always")
def _y(x, p, k, delay, fraction):
    xd = x[p, k - delay] if k - delay >= 0 else 0.0
    return xd - fraction * x[p, k]


@njit(cache=True, nogil=True, parallel=True)
def _dr_cfd_kernel(x, lengths, fraction, delay, arm, dead, search, pre, post, pos, amp, count):
    n = x.shape[0]
    max_echoes = pos.shape[1]
    for p in prange(n):
        length = lengths[p]
        ne = 0
        allowed = 1
        m = 1
        while m < length and ne < max_echoes:
            if m >= allowed and x[p, m] >= arm:
                start = max(allowed, m - delay, 1)
                stop = min(length, m + search)
                found = -1
                for k in range(start, stop):
                    if _y(x, p, k - 1, delay, fraction) < 0.0 and _y(x, p, k, delay, fraction) >= 0.0:
                        found = k
                        break
                if found < 0:
                    m = stop
                    continue
                y0 = _y(x, p, found - 1, delay, fraction)
                y1 = _y(x, p, found, delay, fraction)
                pos[p, ne] = found - 1 + (-y0) / (y1 - y0)
                lo = max(0, found - pre)
                hi = min(length, found + post + 1)
                a = x[p, lo]
                for k in range(lo + 1, hi):
                    if x[p, k] > a:
                        a = x[p, k]
                amp[p, ne] = a
                ne += 1
                allowed = found + dead
                m = found + 1
            else:
                m += 1
        count[p] = ne


def dr_cfd(analog, lengths=None, *, fraction: float, delay_ns: float, arm_dn: float,
           dead_time_ns: float, fwhm_ns: float, max_echoes: int = 4, bin_ns: float = BIN_NS):
    """Run the sensor's DR discriminator on analog waveforms.

    Parameters
    ----------
    analog : (n, m) float64, DN above the baseline
        Noise-free analog signal on a grid of ``bin_ns``.
    lengths : (n,) int, optional
        Valid samples per row (default: all ``m``).
    fraction, delay_ns, arm_dn, dead_time_ns
        CFD fraction f (0-1), delay (ns), arming level (DN, > 0) and dead time (ns).
    fwhm_ns
        FWHM of the system pulse, ns: sets the search and amplitude windows.
    max_echoes
        Most echoes per pulse.

    Returns
    -------
    pos : (n, max_echoes) float64
        Crossing positions in (fractional) bins of the analog grid, NaN-padded.
    amp : (n, max_echoes) float64, DN
        Echo amplitudes, NaN-padded.
    count : (n,) int64
        Echoes per pulse.
    """
    x = np.asarray(analog, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"analog: expected a 2-D array (n, m), got shape {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("analog: non-finite values")
    n, m = x.shape
    if lengths is None:
        lengths = np.full(n, m, dtype=np.int64)
    lengths = np.ascontiguousarray(lengths, dtype=np.int64)
    if lengths.shape != (n,) or np.any(lengths < 0) or np.any(lengths > m):
        raise ValueError(f"lengths: expected (n,) integers in [0, {m}]")
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"fraction: expected 0 < f < 1, got {fraction}")
    if arm_dn <= 0 or delay_ns <= 0 or dead_time_ns < 0 or fwhm_ns <= 0 or bin_ns <= 0:
        raise ValueError("delay_ns, arm_dn, fwhm_ns, bin_ns must be > 0 and dead_time_ns >= 0")
    if max_echoes < 1:
        raise ValueError("max_echoes: expected >= 1")
    x = np.ascontiguousarray(np.where(np.abs(x) < ZERO_DN, 0.0, x))
    delay = max(1, int(round(delay_ns / bin_ns)))
    dead = int(round(dead_time_ns / bin_ns))
    search = max(2, int(round(SEARCH_FWHM * fwhm_ns / bin_ns)))
    pre = int(round(AMP_PRE_FWHM * fwhm_ns / bin_ns))
    post = int(round(AMP_POST_FWHM * fwhm_ns / bin_ns))
    pos = np.full((n, max_echoes), np.nan)
    amp = np.full((n, max_echoes), np.nan)
    count = np.zeros(n, dtype=np.int64)
    if n:
        _dr_cfd_kernel(x, lengths, float(fraction), delay, float(arm_dn), dead, search, pre, post,
                       pos, amp, count)
    return pos, amp, count
