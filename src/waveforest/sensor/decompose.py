"""Gaussian decomposition of waveforms (docs/method.md §(f2); Hofton et al. 2000, Wagner et al. 2006).

Each waveform ``x(t)`` (samples minus the noise mean, DN) is modelled as a sum of Gaussians

    f(t) = sum_k A_k exp(-(t - mu_k)^2 / (2 s_k^2))                                  (F1)

fitted by weighted least squares over the samples within 4 s of any component:

1. **Initial estimates** from the waveform smoothed with a Gaussian of ``s_smooth`` samples:
   each local minimum of its second difference where the smoothed waveform exceeds half the
   detection level is a candidate; its width comes from the two inflection points (zero
   crossings of the second difference) around it, ``s = sqrt((half distance)^2 - s_smooth^2)``,
   its amplitude from the smoothed value scaled by the width lost to smoothing.
2. **Bounded Levenberg–Marquardt** refinement of (A, mu, s) of all components together;
   bounds ``A >= 0``, ``mu`` inside the record, ``s_min <= s <= s_max``. With ``fixed_width``
   every ``s`` stays at ``s_min`` (the system pulse's, a Gaussian approximation of S(t)).
3. **Model selection**: components below the detection level (``min_snr`` noise SDs) are
   dropped and components closer than ``merge_sd`` widths merged, then the fit is repeated;
   a smoothed residual above the detection level adds a component there (at most twice).

Samples at the record's maximum that repeat (a clipped digitiser) get zero weight. A
waveform that is flat, shorter than five samples, or has no candidate above the detection
level gets no echo and a flag (:data:`FLAGS`); no output is ever NaN for a found echo.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

import waveforest.sensor.checks as checks

FLAG_FLAT, FLAG_CLIPPED, FLAG_NOISE, FLAG_SHORT, FLAG_NOT_CONVERGED = 1, 2, 4, 8, 16
FLAGS = {FLAG_FLAT: "flat", FLAG_CLIPPED: "clipped", FLAG_NOISE: "all noise", FLAG_SHORT: "too short",
         FLAG_NOT_CONVERGED: "fit not converged"}
"""Bit flags of a waveform (an int per waveform; several may be set)."""

MIN_SAMPLES = 5
"""Fewer samples than this: too short to fit (three parameters per echo)."""

NP = 3
"""Parameters per echo: amplitude, centre, SD."""

STEP_TOL = 0.01
"""The fit has converged when no centre moves more than this, samples ..."""
COST_TOL = 1e-4
"""... or the weighted squared residual falls by less than this fraction."""


class Decomposition(NamedTuple):
    """Echoes of a table of waveforms, in time order, NaN-padded beyond ``n_echoes``.

    amplitude : (n, k) DN.  time_ns : (n, k) centre, ns from the first sample.
    sigma_ns : (n, k) SD, ns.  n_echoes : (n,) int16.  flags : (n,) uint8 (:data:`FLAGS`).
    rms_residual : (n,) RMS of the fit residual over the fitted samples, DN (NaN: no fit).
    """

    amplitude: np.ndarray
    time_ns: np.ndarray
    sigma_ns: np.ndarray
    n_echoes: np.ndarray
    flags: np.ndarray
    rms_residual: np.ndarray

    @property
    def fwhm_ns(self) -> np.ndarray:
        """Full width at half maximum of each echo, ns."""
        return self.sigma_ns * (2.0 * math.sqrt(2.0 * math.log(2.0)))

    @property
    def energy(self) -> np.ndarray:
        """Area of each echo, DN ns (A s sqrt(2 pi))."""
        return self.amplitude * self.sigma_ns * math.sqrt(2.0 * math.pi)


@njit(cache=True)
def _kernels(s_smooth):
    """A Gaussian smoothing kernel of SD ``s_smooth`` samples (sum 1) and its second difference."""
    r = max(1, int(math.ceil(3.0 * s_smooth)))
    g = np.empty(2 * r + 1)
    for j in range(-r, r + 1):
        g[j + r] = math.exp(-0.5 * (j / s_smooth) ** 2)
    g /= g.sum()
    h = np.zeros(2 * r + 3)
    for j in range(2 * r + 1):  # h = second difference of g, on a grid one sample wider each side
        h[j] += g[j]
        h[j + 1] -= 2.0 * g[j]
        h[j + 2] += g[j]
    return g, h


@njit(cache=True)
def _convolve(x, n, k, out):
    r = (k.size - 1) // 2
    for i in range(n):
        acc = 0.0
        for j in range(k.size):
            m = i + j - r
            if 0 <= m < n:
                acc += k[j] * x[m]
        out[i] = acc


@njit(cache=True)
def _model(t, p, k):
    v = 0.0
    for c in range(k):
        z = (t - p[NP * c + 1]) / p[NP * c + 2]
        if abs(z) < 8.0:
            v += p[NP * c] * math.exp(-0.5 * z * z)
    return v


@njit(cache=True)
def _window(p, k, n):
    lo, hi = n, 0
    for c in range(k):
        a = int(math.floor(p[NP * c + 1] - 4.0 * p[NP * c + 2]))
        b = int(math.ceil(p[NP * c + 1] + 4.0 * p[NP * c + 2]))
        lo, hi = min(lo, a), max(hi, b)
    return max(lo, 0), min(hi + 1, n)


@njit(cache=True)
def _gaussians(p, k, lo, hi, ex):
    """``ex[c, i - lo] = exp(-(i - mu_c)^2 / (2 s_c^2))`` for i in [lo, hi), by the recurrence
    e(i+1) = e(i) r(i), r(i+1) = r(i) exp(-1/s^2), outward from each centre (three exps per
    component instead of one per sample)."""
    for c in range(k):
        mu, s = p[NP * c + 1], p[NP * c + 2]
        inv = 1.0 / (s * s)
        q = math.exp(-inv)
        i0 = min(max(int(round(mu)), lo), hi - 1)
        z = i0 - mu
        e0 = math.exp(-0.5 * z * z * inv)
        ex[c, i0 - lo] = e0
        e, r = e0, math.exp(-(2.0 * z + 1.0) * 0.5 * inv)
        for i in range(i0 + 1, hi):
            e *= r
            r *= q
            ex[c, i - lo] = e
        e, r = e0, math.exp((2.0 * z - 1.0) * 0.5 * inv)
        for i in range(i0 - 1, lo - 1, -1):
            e *= r
            r *= q
            ex[c, i - lo] = e


@njit(cache=True)
def _cost(x, w, p, k, lo, hi, ex):
    _gaussians(p, k, lo, hi, ex)
    s = 0.0
    for i in range(lo, hi):
        r = x[i]
        for c in range(k):
            r -= p[NP * c] * ex[c, i - lo]
        s += w[i] * r * r
    return s


@njit(cache=True)
def _solve(a, b, m):
    """Solve the symmetric positive definite ``a[:m, :m] y = b[:m]`` by Cholesky, in place in b;
    False when ``a`` is not positive definite."""
    for j in range(m):
        d = a[j, j]
        for q in range(j):
            d -= a[j, q] * a[j, q]
        if d <= 0.0:
            return False
        d = math.sqrt(d)
        a[j, j] = d
        for i in range(j + 1, m):
            v = a[i, j]
            for q in range(j):
                v -= a[i, q] * a[j, q]
            a[i, j] = v / d
    for i in range(m):
        v = b[i]
        for q in range(i):
            v -= a[i, q] * b[q]
        b[i] = v / a[i, i]
    for i in range(m - 1, -1, -1):
        v = b[i]
        for q in range(i + 1, m):
            v -= a[q, i] * b[q]
        b[i] = v / a[i, i]
    return True


@njit(cache=True)
def _clamp(p, k, n, s_min, s_max, fixed_width):
    for c in range(k):
        p[NP * c] = max(p[NP * c], 0.0)
        p[NP * c + 1] = min(max(p[NP * c + 1], 0.0), n - 1.0)
        p[NP * c + 2] = s_min if fixed_width else min(max(p[NP * c + 2], s_min), s_max)


@njit(cache=True)
def _levenberg_marquardt(x, w, n, p, k, s_min, s_max, fixed_width, max_iter):
    """Refine ``p[:3k]`` in place (F1, bounds by projection); True when converged."""
    m = NP * k
    jac = np.empty(m)
    hess = np.empty((m, m))
    work = np.empty((m, m))
    grad = np.empty(m)
    step = np.empty(m)
    trial = np.empty(m)
    lam = 1e-3
    lo, hi = _window(p, k, n)  # fixed for this fit: the initial components +- 4 SD, widened by 2 SD
    widest = 0.0
    for c in range(k):
        widest = max(widest, p[NP * c + 2])
    pad = int(2.0 * widest) + 1
    lo, hi = max(lo - pad, 0), min(hi + pad, n)
    ex = np.empty((k, hi - lo))
    cost = _cost(x, w, p, k, lo, hi, ex)
    for _ in range(max_iter):
        hess[:, :] = 0.0
        grad[:] = 0.0
        _gaussians(p, k, lo, hi, ex)
        for i in range(lo, hi):
            if w[i] == 0.0:
                continue
            t = float(i)
            r = x[i]
            for c in range(k):
                a, mu, s = p[NP * c], p[NP * c + 1], p[NP * c + 2]
                z = (t - mu) / s
                e = ex[c, i - lo]
                r -= a * e
                jac[NP * c] = e
                jac[NP * c + 1] = a * e * z / s
                jac[NP * c + 2] = 0.0 if fixed_width else a * e * z * z / s
            wi = w[i]
            for u in range(m):
                ju = wi * jac[u]
                if ju == 0.0:
                    continue
                grad[u] += ju * r
                for v in range(u + 1):
                    hess[u, v] += ju * jac[v]
        improved = False
        for _try in range(8):
            for u in range(m):
                for v in range(u + 1):
                    work[u, v] = hess[u, v]
                work[u, u] = hess[u, u] * (1.0 + lam) + 1e-12
                step[u] = grad[u]
            if not _solve(work, step, m):
                lam *= 10.0
                continue
            for u in range(m):
                trial[u] = p[u] + step[u]
            _clamp(trial, k, n, s_min, s_max, fixed_width)
            new = _cost(x, w, trial, k, lo, hi, ex)
            if new <= cost:
                for u in range(m):
                    p[u] = trial[u]
                lam = max(lam * 0.1, 1e-9)
                improved = True
                small = True
                for c in range(k):
                    small = small and abs(step[NP * c + 1]) < STEP_TOL
                if small or cost - new <= COST_TOL * cost + 1e-12:
                    return True
                cost = new
                break
            lam *= 10.0
        if not improved:
            return True  # no step lowers the cost: a minimum within the bounds
    return False


@njit(cache=True)
def _candidates(xs, d2, n, level, max_k, s_smooth, s_min, s_max, p):
    """Initial (A, mu, s) in ``p`` from minima of the smoothed second difference; their count."""
    k = 0
    for i in range(1, n - 1):
        if d2[i] < 0.0 and d2[i] <= d2[i - 1] and d2[i] < d2[i + 1] and xs[i] > 0.5 * level:
            left = i
            while left > 0 and d2[left] < 0.0:
                left -= 1
            right = i
            while right < n - 1 and d2[right] < 0.0:
                right += 1
            half = 0.5 * (right - left)
            s = math.sqrt(max(half * half - s_smooth * s_smooth, s_min * s_min))
            s = min(max(s, s_min), s_max)
            a = xs[i] * math.sqrt(s * s + s_smooth * s_smooth) / s
            if k < max_k:
                p[NP * k], p[NP * k + 1], p[NP * k + 2] = a, float(i), s
                k += 1
            else:  # full: replace the weakest when this one is stronger
                weakest = 0
                for c in range(1, k):
                    if p[NP * c] < p[NP * weakest]:
                        weakest = c
                if a > p[NP * weakest]:
                    p[NP * weakest], p[NP * weakest + 1], p[NP * weakest + 2] = a, float(i), s
    return k


@njit(cache=True)
def _prune(p, k, level, merge_sd):
    """Drop components below ``level``; merge pairs closer than ``merge_sd`` widths; sort by time."""
    q = 0
    for c in range(k):
        if p[NP * c] >= level:
            for j in range(NP):
                p[NP * q + j] = p[NP * c + j]
            q += 1
    k = q
    for a in range(1, k):  # insertion sort by centre
        j = a
        while j > 0 and p[NP * j + 1] < p[NP * (j - 1) + 1]:
            for u in range(NP):
                p[NP * j + u], p[NP * (j - 1) + u] = p[NP * (j - 1) + u], p[NP * j + u]
            j -= 1
    c = 0
    while c < k - 1:
        gap = p[NP * (c + 1) + 1] - p[NP * c + 1]
        if gap < merge_sd * max(p[NP * c + 2], p[NP * (c + 1) + 2]):
            a1, a2 = p[NP * c], p[NP * (c + 1)]
            tot = a1 + a2
            p[NP * c + 1] = (a1 * p[NP * c + 1] + a2 * p[NP * (c + 1) + 1]) / tot
            p[NP * c] = max(a1, a2)
            p[NP * c + 2] = max(p[NP * c + 2], p[NP * (c + 1) + 2])
            for d in range(c + 1, k - 1):
                for u in range(NP):
                    p[NP * d + u] = p[NP * (d + 1) + u]
            k -= 1
        else:
            c += 1
    return k


@njit(cache=True)
def decompose_row(x, n, dt, mean, sd, s_min_ns, s_max_ns, min_snr, merge_sd, fixed_width, s_smooth,
                  max_iter, out_p):
    """Decompose one waveform (module docstring); echoes into ``out_p`` ((max_k, 3): A DN, mu ns,
    s ns). Returns (echo count, flags, RMS residual DN)."""
    max_k = out_p.shape[0]
    if n < MIN_SAMPLES:
        return 0, FLAG_SHORT, np.nan
    y = np.empty(n)
    w = np.ones(n)
    hi_v, lo_v = -np.inf, np.inf
    for i in range(n):
        y[i] = x[i] - mean
        hi_v, lo_v = max(hi_v, x[i]), min(lo_v, x[i])
    if not (hi_v - lo_v > 1e-9):
        return 0, FLAG_FLAT, np.nan
    flags = 0
    for i in range(n - 1):  # a repeated record maximum: the digitiser clipped
        if x[i] == hi_v and x[i + 1] == hi_v:
            flags |= FLAG_CLIPPED
            break
    if flags & FLAG_CLIPPED:
        for i in range(n):
            if x[i] == hi_v:
                w[i] = 0.0
    s_min, s_max = s_min_ns / dt, s_max_ns / dt
    level = min_snr * sd
    g, h = _kernels(s_smooth)
    xs = np.empty(n)
    d2 = np.empty(n)
    _convolve(y, n, g, xs)
    _convolve(y, n, h, d2)
    cap = 2 * max_k + 2
    p = np.empty(NP * cap)
    k = _candidates(xs, d2, n, level, cap, s_smooth, s_min, s_max, p)
    if k == 0:
        return 0, flags | FLAG_NOISE, np.nan
    converged = _levenberg_marquardt(y, w, n, p, k, s_min, s_max, fixed_width, max_iter)
    for _added in range(3):
        before = k
        k = _prune(p, k, level, merge_sd)
        while k > max_k:  # keep the strongest max_k
            weakest = 0
            for c in range(1, k):
                if p[NP * c] < p[NP * weakest]:
                    weakest = c
            for d in range(weakest, k - 1):
                for u in range(NP):
                    p[NP * d + u] = p[NP * (d + 1) + u]
            k -= 1
        if k == 0:
            break
        if k != before:
            converged = _levenberg_marquardt(y, w, n, p, k, s_min, s_max, fixed_width, max_iter)
            k = _prune(p, k, level, merge_sd)
        if k >= max_k or k == 0:
            break
        # a residual echo the candidates missed: add it and refit
        for i in range(n):
            d2[i] = y[i] - _model(float(i), p, k)
        _convolve(d2, n, g, xs)
        best, at = 0.0, -1
        for i in range(n):
            if w[i] > 0.0 and xs[i] > best:
                best, at = xs[i], i
        if best <= level:
            break
        p[NP * k], p[NP * k + 1], p[NP * k + 2] = best, float(at), max(s_min, min(s_max, 2.0 * s_smooth))
        k += 1
        converged = _levenberg_marquardt(y, w, n, p, k, s_min, s_max, fixed_width, max_iter)
    if k == 0:
        return 0, flags | FLAG_NOISE, np.nan
    lo, hi = _window(p, k, n)
    ss, nw = 0.0, 0.0
    for i in range(lo, hi):
        r = y[i] - _model(float(i), p, k)
        ss += w[i] * r * r
        nw += w[i]
    for c in range(k):
        out_p[c, 0] = p[NP * c]
        out_p[c, 1] = p[NP * c + 1] * dt
        out_p[c, 2] = p[NP * c + 2] * dt
    if not converged:
        flags |= FLAG_NOT_CONVERGED
    return k, flags, math.sqrt(ss / max(nw, 1.0))


@njit(parallel=True, cache=True)
def _decompose_kernel(samples, lengths, dt, mean, sd, s_min_ns, s_max_ns, min_snr, merge_sd, fixed_width,
                      smooth_ns, max_iter, out_p, out_k, out_flags, out_rms):
    for i in prange(samples.shape[0]):
        s_smooth = max(0.5, smooth_ns / dt[i])
        k, f, rms = decompose_row(samples[i], lengths[i], dt[i], mean[i], sd[i], s_min_ns, s_max_ns, min_snr,
                                  merge_sd, fixed_width, s_smooth, max_iter, out_p[i])
        out_k[i], out_flags[i], out_rms[i] = k, f, rms


def decompose(samples, lengths, sampling_ns, noise_mean, noise_sd, *, pulse_fwhm_ns: float | None = None,
              fixed_width: bool = False, min_snr: float = 3.0, max_echoes: int = 8, merge_sd: float = 1.0,
              max_width_factor: float = 6.0, max_iter: int = 30) -> Decomposition:
    """Gaussian decomposition of every waveform of a table (module docstring, Eq. F1).

    Parameters
    ----------
    samples : (n, n_s) DN, NaN-padded beyond ``lengths``.  lengths : (n,) int or None.
    sampling_ns : float or (n,), ns.  noise_mean, noise_sd : float or (n,), DN.
    pulse_fwhm_ns : FWHM of the system pulse, ns: the narrowest echo (s_min) and, with
        ``fixed_width``, every echo's width; None: s_min is half a sample and echoes are free.
    min_snr : detection level, noise SDs of amplitude.  max_echoes : most echoes per waveform.
    merge_sd : components closer than this many widths are one echo.
    max_width_factor : widest echo, in units of s_min (or of two samples without a pulse).
    """
    x, lens = checks.waveforms(samples, lengths)
    n = x.shape[0]
    if int(max_echoes) < 1:
        raise ValueError(f"max_echoes must be >= 1, got {max_echoes}")
    if fixed_width and pulse_fwhm_ns is None:
        raise ValueError("fixed_width needs pulse_fwhm_ns")
    dt = checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    mean = checks.per_pulse(noise_mean, n, "noise_mean")
    sd = checks.per_pulse(noise_sd, n, "noise_sd", nonnegative=True)
    fwhm_to_sd = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    s_min = float(pulse_fwhm_ns) * fwhm_to_sd if pulse_fwhm_ns else 0.5 * float(np.min(dt, initial=1.0))
    s_max = max_width_factor * (s_min if pulse_fwhm_ns else 2.0 * float(np.max(dt, initial=1.0)))
    smooth_ns = 0.5 * s_min if pulse_fwhm_ns else float(np.min(dt, initial=1.0))
    out = np.full((n, int(max_echoes), 3), np.nan)
    k = np.zeros(n, np.int64)
    flags = np.zeros(n, np.int64)
    rms = np.full(n, np.nan)
    if n:
        _decompose_kernel(x, lens, dt, mean, sd, s_min, s_max, float(min_snr), float(merge_sd), bool(fixed_width),
                          smooth_ns, int(max_iter), out, k, flags, rms)
    return Decomposition(out[:, :, 0], out[:, :, 1], out[:, :, 2], k.astype(np.int16), flags.astype(np.uint8), rms)
