"""Gaussian decomposition of waveforms (docs/method.md §(f2); Hofton et al. 2000, Wagner et al. 2006).

Each waveform ``x(t)`` (samples minus the noise mean, DN) is modelled as a sum of Gaussians

    f(t) = sum_k A_k exp(-(t - mu_k)^2 / (2 s_k^2))                                  (F1)

fitted by weighted least squares over the samples within 4 s of any component:

1. **Initial estimates** from the waveform smoothed with a Gaussian of ``s_smooth`` samples
   (variance ``v``): each local minimum of its second difference where the smoothed waveform
   exceeds half the detection level is a candidate; its width comes from the two inflection
   points (interpolated zero crossings of the second difference) around it,
   ``s = sqrt((half distance)^2 - v - 1/6)``, its amplitude from the smoothed value scaled by
   the width lost to smoothing. Candidates closer than ``merge_sd`` widths are merged, and the
   amplitudes are solved for (linear least squares) before the first step.
2. **Bounded Levenberg–Marquardt** refinement of (A, mu, s) of all components together, with
   the analytic Jacobian and, while it is positive definite, the exact Hessian (the residual's
   second-derivative term added to Gauss–Newton's, which otherwise converges only linearly for
   weak echoes); each component is evaluated within ``TRUNC`` SDs of its centre, so the normal
   equations of components that do not overlap are independent blocks. Bounds
   ``0 <= A <= A_max`` (:data:`AMP_BOUND`), ``mu`` inside the fitted samples (never outside
   the record), ``s_min <= s <= s_max``. With ``fixed_width`` every ``s`` stays at ``s_min``
   (the system pulse's, a Gaussian approximation of S(t)).
3. **Model selection**: components below the detection level (``min_snr`` noise SDs) are
   dropped and components closer than ``merge_sd`` widths merged, then the fit is repeated;
   a smoothed residual above the detection level adds a component there (at most three times).
   An added component that does not survive the selection is taken back with its refit: the
   fit before it is kept. The echoes returned are always those of a fit, never of an unfitted
   merge.

Samples at the record's maximum get zero weight where the digitiser clipped: the maximum held
over two samples or more at a full-scale value 2^k - 1 (:data:`FULL_SCALE_BITS`). A
waveform that is flat, shorter than five samples, or has no candidate above the detection
level gets no echo and a flag (:data:`FLAGS`); no output is ever NaN for a found echo. A fit
that did not converge, or whose residual is far above the noise (:data:`POOR_FIT_SD`,
:data:`POOR_FIT_PEAK`), keeps its echoes and is flagged.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

import waveforest.sensor.checks as checks

FLAG_FLAT, FLAG_CLIPPED, FLAG_NOISE, FLAG_SHORT, FLAG_NOT_CONVERGED, FLAG_POOR_FIT = 1, 2, 4, 8, 16, 32
FLAGS = {FLAG_FLAT: "flat", FLAG_CLIPPED: "clipped", FLAG_NOISE: "all noise", FLAG_SHORT: "too short",
         FLAG_NOT_CONVERGED: "fit not converged", FLAG_POOR_FIT: "poor fit"}
"""Bit flags of a waveform (an int per waveform; several may be set)."""

POOR_FIT_SD = 5.0
"""A fit is poor when its RMS residual exceeds this many noise SDs ..."""
POOR_FIT_PEAK = 0.05
"""... plus this fraction of the record's highest sample above the noise mean (a real
system pulse is no exact Gaussian: its misfit grows with the echo)."""
AMP_BOUND = 2.0
"""An echo's amplitude is at most this many times the record's highest sample above the
noise mean, plus the detection level (components are non-negative, so none exceeds the data
by more than the noise, except between samples: a Gaussian of SD half a sample peaks 1.65
times above its nearest sample); unbounded where the record was clipped."""

MIN_SAMPLES = 5
"""Fewer samples than this: too short to fit (three parameters per echo)."""

NP = 3
"""Parameters per echo: amplitude, centre, SD."""

STEP_TOL = 0.01
"""The fit has converged when no centre or width moves more than this, samples ..."""
COST_TOL = 1e-4
"""... or the weighted squared residual falls by less than this fraction."""
SLOW_FIT = 1
"""Steps after which a fit whose components would be pruned or merged stops early."""


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


TRUNC = 5.0
"""Each component is evaluated within this many SDs of its centre (exp(-12.5) = 4e-6 beyond)."""

BLOCK = 64
FAST = {"reassoc", "contract"}
"""Numba fast-math flags of the sums over samples (reordered, fused; no NaN or inf assumptions)."""
"""Waveforms per parallel work unit (each unit allocates its scratch arrays once)."""


@njit(cache=True)
def _kernel(s_smooth):
    """A Gaussian smoothing kernel of SD ``s_smooth`` samples (sum 1) and its variance, samples^2."""
    r = max(1, int(math.ceil(3.0 * s_smooth)))
    g = np.empty(2 * r + 1)
    for j in range(-r, r + 1):
        g[j + r] = math.exp(-0.5 * (j / s_smooth) ** 2)
    g /= g.sum()
    var = 0.0
    for j in range(-r, r + 1):
        var += j * j * g[j + r]
    return g, var


@njit(cache=True, fastmath=FAST)
def _smooth(x, n, g, out):
    """``out[i + 1] = sum_j g[j] x[i + j - r]`` for i in [-1, n] (x zero outside [0, n)): the
    smoothed waveform one sample beyond each end, so its second difference covers [0, n)."""
    r = (g.size - 1) // 2
    out[: n + 2] = 0.0
    for j in range(g.size):  # tap by tap over views from 0: the inner loop vectorises
        gj = g[j]
        off = j - r - 1
        lo, hi = max(0, -off), min(n + 2, n - off)
        ov, xv = out[lo:hi], x[lo + off:hi + off]
        for q in range(hi - lo):
            ov[q] += gj * xv[q]


@njit(cache=True)
def _second_difference(xs_ext, n, d2):
    a, b, c = xs_ext[:n], xs_ext[1:n + 1], xs_ext[2:n + 2]
    for i in range(n):
        d2[i] = c[i] - 2.0 * b[i] + a[i]


@njit(cache=True)
def _window(p, k, n):
    lo, hi = n, 0
    for c in range(k):
        a = int(math.floor(p[NP * c + 1] - 4.0 * p[NP * c + 2]))
        b = int(math.ceil(p[NP * c + 1] + 4.0 * p[NP * c + 2]))
        lo, hi = min(lo, a), max(hi, b)
    return max(lo, 0), min(hi + 1, n)


@njit(cache=True)
def _gaussian(mu, s, m, e):
    """``e[i] = exp(-(i - mu)^2 / (2 s^2))`` for i in [0, m), by the recurrence
    e(i+1) = e(i) r(i), r(i+1) = r(i) exp(-1/s^2), outward from the centre (three exps, not one
    per sample)."""
    inv = 1.0 / (s * s)
    q = math.exp(-inv)
    i0 = min(max(int(round(mu)), 0), m - 1)
    z = i0 - mu
    e0 = math.exp(-0.5 * z * z * inv)
    e[i0] = e0
    v, r = e0, math.exp(-(2.0 * z + 1.0) * 0.5 * inv)
    for i in range(i0 + 1, m):
        v *= r
        r *= q
        e[i] = v
    v, r = e0, math.exp((2.0 * z - 1.0) * 0.5 * inv)
    for i in range(i0 - 1, -1, -1):
        v *= r
        r *= q
        e[i] = v


@njit(cache=True, fastmath=FAST)
def _residual(y, w, p, k, lo, hi, ex, sup, r):
    """``r[lo:hi] = y - f`` (Eq. F1, each component within TRUNC SDs: ``ex[c, sup[c, 0]:sup[c, 1]]``,
    its unit Gaussian); returns the weighted squared residual over [lo, hi). (Loops run over
    views from 0 so that they vectorise.)"""
    rv, yv, wv = r[lo:hi], y[lo:hi], w[lo:hi]
    for i in range(hi - lo):
        rv[i] = yv[i]
    for c in range(k):
        mu, s = p[NP * c + 1], p[NP * c + 2]
        a = max(lo, int(math.floor(mu - TRUNC * s)))
        b = max(a, min(hi, int(math.ceil(mu + TRUNC * s)) + 1))
        sup[c, 0], sup[c, 1] = a, b
        if a == b:
            continue
        e, rc = ex[c, a:b], r[a:b]
        _gaussian(mu - a, s, b - a, e)
        amp = p[NP * c]
        for i in range(b - a):
            rc[i] -= amp * e[i]
    ss = 0.0
    for i in range(hi - lo):
        ss += wv[i] * rv[i] * rv[i]
    return ss


@njit(cache=True, fastmath=FAST)
def _normal_equations(p, k, w, r, ex, sup, fixed_width, jac, grad, hess, second):
    """Gradient ``J^T W r`` and lower triangle of ``J^T W J`` of Eq. F1 (analytic Jacobian),
    each component's rows over its support only, blocks of non-overlapping pairs zero; and
    ``second[c]``, the lower triangle (AA, mA, mm, sA, sm, ss) of ``sum_i w r d2f/dp dp`` of
    component c (the residual's term of the exact Hessian, zero between components)."""
    m = NP * k
    for u in range(m):
        for v in range(u + 1):
            hess[u, v] = 0.0
    for c in range(k):
        a, b = sup[c, 0], sup[c, 1]
        amp, m0, s = p[NP * c], p[NP * c + 1] - a, p[NP * c + 2]
        inv = 1.0 / s
        fs = 0.0 if fixed_width else 1.0
        u = NP * c
        e, wc, rc = ex[c, a:b], w[a:b], r[a:b]
        j0, j1, j2 = jac[u, a:b], jac[u + 1, a:b], jac[u + 2, a:b]
        g0 = g1 = g2 = h00 = h10 = h11 = h20 = h21 = h22 = 0.0
        s10 = s11 = s20 = s21 = s22 = 0.0
        for i in range(b - a):
            z = (i - m0) * inv
            ei = e[i]
            d1 = amp * ei * inv * z
            d2 = fs * d1 * z
            j0[i], j1[i], j2[i] = ei, d1, d2
            wi = wc[i]
            wr = wi * rc[i]
            g0 += wr * ei
            g1 += wr * d1
            g2 += wr * d2
            # second derivatives: f_Am = e z/s, f_mm = A e (z^2 - 1)/s^2, f_As = e z^2/s,
            # f_ms = A e (z^3 - 2z)/s^2, f_ss = A e (z^4 - 3z^2)/s^2
            we = wr * ei * inv
            wa = we * amp * inv
            z2 = z * z
            s10 += we * z
            s11 += wa * (z2 - 1.0)
            s20 += we * z2
            s21 += wa * z * (z2 - 2.0)
            s22 += wa * z2 * (z2 - 3.0)
            w0, w1, w2 = wi * ei, wi * d1, wi * d2
            h00 += w0 * ei
            h10 += w1 * ei
            h11 += w1 * d1
            h20 += w2 * ei
            h21 += w2 * d1
            h22 += w2 * d2
        grad[u], grad[u + 1], grad[u + 2] = g0, g1, g2
        hess[u, u], hess[u + 1, u], hess[u + 1, u + 1] = h00, h10, h11
        hess[u + 2, u], hess[u + 2, u + 1], hess[u + 2, u + 2] = h20, h21, h22
        second[c, 0], second[c, 1], second[c, 2] = 0.0, s10, s11
        second[c, 3], second[c, 4], second[c, 5] = fs * s20, fs * s21, fs * s22
        for d in range(k):  # blocks with the components before c (columns < u): the lower triangle
            if d >= c:
                break
            a2, b2 = max(a, sup[d, 0]), min(b, sup[d, 1])
            if a2 >= b2:
                continue
            v = NP * d
            wc = w[a2:b2]
            p0, p1, p2 = jac[u, a2:b2], jac[u + 1, a2:b2], jac[u + 2, a2:b2]
            q0, q1, q2 = jac[v, a2:b2], jac[v + 1, a2:b2], jac[v + 2, a2:b2]
            c00 = c01 = c02 = c10 = c11 = c12 = c20 = c21 = c22 = 0.0
            for i in range(b2 - a2):
                wi = wc[i]
                w0, w1, w2 = wi * p0[i], wi * p1[i], wi * p2[i]
                k0, k1, k2 = q0[i], q1[i], q2[i]
                c00 += w0 * k0
                c01 += w0 * k1
                c02 += w0 * k2
                c10 += w1 * k0
                c11 += w1 * k1
                c12 += w1 * k2
                c20 += w2 * k0
                c21 += w2 * k1
                c22 += w2 * k2
            hess[u, v], hess[u, v + 1], hess[u, v + 2] = c00, c01, c02
            hess[u + 1, v], hess[u + 1, v + 1], hess[u + 1, v + 2] = c10, c11, c12
            hess[u + 2, v], hess[u + 2, v + 1], hess[u + 2, v + 2] = c20, c21, c22


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
def _clamp(p, k, lo, hi, a_max, s_min, s_max, fixed_width):
    """Project ``p`` onto the bounds: ``0 <= A <= a_max``, ``lo <= mu <= hi - 1`` (the fitted
    samples), ``s_min <= s <= s_max``."""
    for c in range(k):
        p[NP * c] = min(max(p[NP * c], 0.0), a_max)
        p[NP * c + 1] = min(max(p[NP * c + 1], float(lo)), hi - 1.0)
        p[NP * c + 2] = s_min if fixed_width else min(max(p[NP * c + 2], s_min), s_max)


class Scratch(NamedTuple):
    """Work arrays of one thread (:func:`scratch`); nothing is allocated per waveform."""

    y: np.ndarray
    w: np.ndarray
    xs: np.ndarray
    d2: np.ndarray
    r: np.ndarray
    r2: np.ndarray
    ex: np.ndarray
    ex2: np.ndarray
    sup: np.ndarray
    sup2: np.ndarray
    jac: np.ndarray
    p: np.ndarray
    trial: np.ndarray
    step: np.ndarray
    grad: np.ndarray
    hess: np.ndarray
    work: np.ndarray
    second: np.ndarray
    saved: np.ndarray


@njit(cache=True)
def scratch(n_samples, max_k):
    """Work arrays for waveforms of up to ``n_samples`` samples and ``max_k`` echoes."""
    cap = 2 * max_k + 2
    m = NP * cap
    return Scratch(np.empty(n_samples), np.empty(n_samples), np.empty(n_samples + 2), np.empty(n_samples),
                   np.empty(n_samples), np.empty(n_samples), np.empty((cap, n_samples)),
                   np.empty((cap, n_samples)), np.empty((cap, 2), np.int64), np.empty((cap, 2), np.int64),
                   np.empty((m, n_samples)), np.empty(m), np.empty(m), np.empty(m), np.empty(m),
                   np.empty((m, m)), np.empty((m, m)), np.empty((cap, 6)), np.empty(m))


@njit(cache=True)
def _levenberg_marquardt(ws, n, k, a_max, s_min, s_max, fixed_width, max_iter, level, merge_sd, amplitudes_first):
    """Refine ``ws.p[:3k]`` in place (F1, bounds by projection, :func:`_clamp`); True when
    converged. The fit runs over the initial components +- 4 SD, widened by 2 SD of the widest,
    and keeps every centre within those samples (a component outside them would be free of the
    data: any amplitude at no cost). Steps use the
    exact Hessian (second derivatives of F1) where it is positive definite, else Gauss-Newton's;
    after SLOW_FIT steps a fit that :func:`_prune` would change stops early (False): two
    components sharing one echo slide along a flat valley of the cost, and the pruned set is
    refitted instead."""
    y, w, p, trial, step, grad, hess, work = ws.y, ws.w, ws.p, ws.trial, ws.step, ws.grad, ws.hess, ws.work
    ex, sup, r, ex_t, sup_t, r_t = ws.ex, ws.sup, ws.r, ws.ex2, ws.sup2, ws.r2
    m = NP * k
    lam = 1e-3
    lo, hi = _window(p, k, n)
    widest = 0.0
    for c in range(k):
        widest = max(widest, p[NP * c + 2])
    pad = int(2.0 * widest) + 1
    lo, hi = max(lo - pad, 0), min(hi + pad, n)
    _clamp(p, k, lo, hi, a_max, s_min, s_max, fixed_width)
    cost = _residual(y, w, p, k, lo, hi, ex, sup, r)
    if amplitudes_first:  # the amplitudes that fit best for these centres and widths: linear
        _normal_equations(p, k, w, r, ex, sup, fixed_width, ws.jac, grad, hess, ws.second)
        for c in range(k):
            for d in range(c + 1):
                work[c, d] = hess[NP * c, NP * d]
            work[c, c] += 1e-12
            step[c] = grad[NP * c]
        if _solve(work, step, k):
            for u in range(m):
                trial[u] = p[u]
            for c in range(k):
                trial[NP * c] = min(max(p[NP * c] + step[c], 0.0), a_max)
            new = _residual(y, w, trial, k, lo, hi, ex_t, sup_t, r_t)
            if new < cost:
                for u in range(m):
                    p[u] = trial[u]
                ex, ex_t, sup, sup_t, r, r_t = ex_t, ex, sup_t, sup, r_t, r
                cost = new
    for it in range(max_iter):
        if it >= SLOW_FIT and _prunable(p, k, level, merge_sd):
            return False
        _normal_equations(p, k, w, r, ex, sup, fixed_width, ws.jac, grad, hess, ws.second)
        improved = False
        newton = True  # the exact Hessian while it is positive definite, else Gauss-Newton's
        for _try in range(9):
            for u in range(m):
                for v in range(u + 1):
                    work[u, v] = hess[u, v]
                work[u, u] += hess[u, u] * lam + 1e-12
                step[u] = grad[u]
            if newton:
                for c in range(k):
                    u = NP * c
                    sc = ws.second[c]
                    work[u + 1, u] -= sc[1]
                    work[u + 1, u + 1] -= sc[2]
                    work[u + 2, u] -= sc[3]
                    work[u + 2, u + 1] -= sc[4]
                    work[u + 2, u + 2] -= sc[5]
            if not _solve(work, step, m):
                if newton:
                    newton = False
                else:
                    lam *= 10.0
                continue
            for u in range(m):
                trial[u] = p[u] + step[u]
            _clamp(trial, k, lo, hi, a_max, s_min, s_max, fixed_width)
            new = _residual(y, w, trial, k, lo, hi, ex_t, sup_t, r_t)
            if new <= cost:
                small = True  # the move within the bounds, not the step asked for
                for c in range(k):
                    small = (small and abs(trial[NP * c + 1] - p[NP * c + 1]) < STEP_TOL
                             and abs(trial[NP * c + 2] - p[NP * c + 2]) < STEP_TOL)
                for u in range(m):
                    p[u] = trial[u]
                ex, ex_t, sup, sup_t, r, r_t = ex_t, ex, sup_t, sup, r_t, r
                lam = max(lam * 0.1, 1e-9)
                improved = True
                if small or cost - new <= COST_TOL * cost + 1e-12:
                    return True
                cost = new
                break
            lam *= 10.0
        if not improved:
            return True  # no step lowers the cost: a minimum within the bounds
    return False


@njit(cache=True)
def _candidates(xs, d2, n, level, max_k, var_smooth, s_min, s_max, p):
    """Initial (A, mu, s) in ``p`` from minima of the smoothed second difference; their count.
    The centre is the minimum's sample, the width half the distance between the linearly
    interpolated zero crossings around it (a Gaussian of SD s smoothed has them at
    +- sqrt(s^2 + var_smooth + 1/6), 1/6 the second difference's own variance)."""
    k = 0
    for i in range(1, n - 1):
        if d2[i] < 0.0 and d2[i] <= d2[i - 1] and d2[i] < d2[i + 1] and xs[i] > 0.5 * level:
            left = i
            while left > 0 and d2[left] < 0.0:
                left -= 1
            right = i
            while right < n - 1 and d2[right] < 0.0:
                right += 1
            t_left = left + d2[left] / (d2[left] - d2[left + 1]) if d2[left] >= 0.0 else float(left)
            t_right = right - d2[right] / (d2[right] - d2[right - 1]) if d2[right] >= 0.0 else float(right)
            half = 0.5 * (t_right - t_left)
            s = math.sqrt(max(half * half - var_smooth - 1.0 / 6.0, s_min * s_min))
            s = min(max(s, s_min), s_max)
            mu = float(i)
            a = xs[i] * math.sqrt(s * s + var_smooth) / s
            if k < max_k:
                p[NP * k], p[NP * k + 1], p[NP * k + 2] = a, mu, s
                k += 1
            else:  # full: replace the weakest when this one is stronger
                weakest = 0
                for c in range(1, k):
                    if p[NP * c] < p[NP * weakest]:
                        weakest = c
                if a > p[NP * weakest]:
                    p[NP * weakest], p[NP * weakest + 1], p[NP * weakest + 2] = a, mu, s
    return k


@njit(cache=True)
def _merge(p, k, merge_sd, s_lo, s_hi):
    """Merge neighbours (``p`` sorted by centre) closer than ``merge_sd`` widths into one
    Gaussian of the same area, mean and variance (clamped to [s_lo, s_hi]); the count left."""
    c = 0
    while c < k - 1:
        u, v = NP * c, NP * (c + 1)
        if p[v + 1] - p[u + 1] < merge_sd * max(p[u + 2], p[v + 2]):
            e1, e2 = p[u] * p[u + 2], p[v] * p[v + 2]
            tot = e1 + e2
            if tot > 0.0:
                mu = (e1 * p[u + 1] + e2 * p[v + 1]) / tot
                var = (e1 * (p[u + 2] ** 2 + (p[u + 1] - mu) ** 2) + e2 * (p[v + 2] ** 2 + (p[v + 1] - mu) ** 2)) / tot
                sd = min(max(math.sqrt(var), s_lo), s_hi)
                p[u], p[u + 1], p[u + 2] = tot / sd, mu, sd
            for d in range(c + 1, k - 1):
                for j in range(NP):
                    p[NP * d + j] = p[NP * (d + 1) + j]
            k -= 1
        else:
            c += 1
    return k


@njit(cache=True)
def _prune(p, k, level, merge_sd, s_lo, s_hi):
    """Drop components below ``level``; sort by time; :func:`_merge`."""
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
    return _merge(p, k, merge_sd, s_lo, s_hi)


@njit(cache=True)
def _select(p, k, level, merge_sd, s_lo, s_hi, max_k):
    """:func:`_prune`, then keep the strongest ``max_k``; the count left."""
    k = _prune(p, k, level, merge_sd, s_lo, s_hi)
    while k > max_k:
        weakest = 0
        for c in range(1, k):
            if p[NP * c] < p[NP * weakest]:
                weakest = c
        for d in range(weakest, k - 1):
            for u in range(NP):
                p[NP * d + u] = p[NP * (d + 1) + u]
        k -= 1
    return k


@njit(cache=True)
def _prunable(p, k, level, merge_sd):
    """True when :func:`_prune` would drop or merge a component."""
    for c in range(k):
        if p[NP * c] < level:
            return True
        for d in range(c):
            if abs(p[NP * c + 1] - p[NP * d + 1]) < merge_sd * max(p[NP * c + 2], p[NP * d + 2]):
                return True
    return False


FULL_SCALE_BITS = (8, 16)
"""A record maximum held over two samples or more is a clipped digitiser only at a full-scale
value 2^k - 1, k in this range (8-bit to 16-bit digitisers, 12- and 14-bit ones in 16-bit
words): equal top samples at other values are common (an echo whose peak lies midway between
two samples; a canopy echo wider than the pulse: 20 % and 2 % of the virtual campaign's
waveforms, none of them at 255, docs/validation.md)."""


@njit(cache=True)
def _clipped(x, n, hi_v, mean, agc_gain):
    """Whether the record ``x[:n]`` with maximum ``hi_v`` was clipped (:data:`FULL_SCALE_BITS`):
    the raw maximum ``(hi_v - mean) agc_gain + mean`` (the samples of an AGC-normalised table
    are (V - n0) / g + n0, Eq. 1) within half a DN of 2^k - 1, held over two samples or more."""
    raw = (hi_v - mean) * agc_gain + mean
    full = False
    for k in range(FULL_SCALE_BITS[0], FULL_SCALE_BITS[1] + 1):
        full = full or abs(raw - (2.0 ** k - 1.0)) < 0.5
    if not full:
        return False
    for i in range(n - 1):
        if x[i] == hi_v and x[i + 1] == hi_v:
            return True
    return False


@njit(cache=True)
def decompose_row(x, n, dt, mean, sd, agc_gain, s_min_ns, s_max_ns, min_snr, merge_sd, fixed_width, g,
                  var_smooth, max_iter, ws, out_p):
    """Decompose one waveform (module docstring; ``agc_gain`` the gain its samples were divided
    by, 1 for raw samples) with the smoothing kernel ``g`` (variance
    ``var_smooth``, samples^2; :func:`_kernel`) and the work
    arrays ``ws`` (:func:`scratch`); echoes into ``out_p`` ((max_k, 3): A DN, mu ns, s ns).
    Returns (echo count, flags, RMS residual DN)."""
    max_k = out_p.shape[0]
    if n < MIN_SAMPLES:
        return 0, FLAG_SHORT, np.nan
    y, w, xs, d2, p = ws.y, ws.w, ws.xs, ws.d2, ws.p
    hi_v, lo_v = -np.inf, np.inf
    for i in range(n):
        y[i] = x[i] - mean
        w[i] = 1.0
        hi_v, lo_v = max(hi_v, x[i]), min(lo_v, x[i])
    if not (hi_v - lo_v > 1e-9):
        return 0, FLAG_FLAT, np.nan
    flags = 0
    if _clipped(x, n, hi_v, mean, agc_gain):
        flags |= FLAG_CLIPPED
    if flags & FLAG_CLIPPED:
        for i in range(n):
            if x[i] == hi_v:
                w[i] = 0.0
    s_min, s_max = s_min_ns / dt, s_max_ns / dt
    level = min_snr * sd
    peak = hi_v - mean
    a_max = np.inf if flags & FLAG_CLIPPED else AMP_BOUND * peak + level
    _smooth(y, n, g, xs)
    _second_difference(xs, n, d2)
    cap = ws.ex.shape[0]
    s_hi = s_min if fixed_width else s_max
    k = _candidates(xs[1:], d2, n, level, cap, var_smooth, s_min, s_hi, p)
    if k == 0:
        return 0, flags | FLAG_NOISE, np.nan
    k = _prune(p, k, 0.0, merge_sd, s_min, s_hi)  # two minima within one echo: noise on its top
    converged = _levenberg_marquardt(ws, n, k, a_max, s_min, s_max, fixed_width, max_iter, level, merge_sd, True)
    added = 0
    k_saved, converged_saved = -1, False  # the fit before a component was added (-1: none)
    # each round drops a component, adds one (three at most) or ends: the loop ends in a break
    for _round in range(cap + 8):
        before = k
        k = _select(p, k, level, merge_sd, s_min, s_hi, max_k)
        if k != before and k <= k_saved:  # the added component did not survive: the fit before it
            for u in range(NP * k_saved):
                p[u] = ws.saved[u]
            k, converged = k_saved, converged_saved
            break
        if k == 0:
            break
        if k != before:  # refit what is left, then select again
            converged = _levenberg_marquardt(ws, n, k, a_max, s_min, s_max, fixed_width, max_iter, level, merge_sd,
                                             False)
            continue
        k_saved = -1
        if k >= max_k or added == 3:
            break
        # a residual echo the candidates missed: add it and refit
        _residual(y, w, p, k, 0, n, ws.ex, ws.sup, d2)
        _smooth(d2, n, g, xs)
        best, at = 0.0, -1
        for i in range(n):
            if w[i] > 0.0 and xs[i + 1] > best:
                best, at = xs[i + 1], i
        if best <= level:
            break
        for u in range(NP * k):
            ws.saved[u] = p[u]
        k_saved, converged_saved = k, converged
        p[NP * k], p[NP * k + 1], p[NP * k + 2] = best, float(at), max(s_min, min(s_max, 2.0 * math.sqrt(var_smooth)))
        k += 1
        added += 1
        converged = _levenberg_marquardt(ws, n, k, a_max, s_min, s_max, fixed_width, max_iter, level, merge_sd, True)
    if k == 0:
        return 0, flags | FLAG_NOISE, np.nan
    lo, hi = _window(p, k, n)
    _residual(y, w, p, k, 0, n, ws.ex, ws.sup, d2)
    ss, nw = 0.0, 0.0
    for i in range(lo, hi):
        ss += w[i] * d2[i] * d2[i]
        nw += w[i]
    for c in range(k):
        out_p[c, 0] = p[NP * c]
        out_p[c, 1] = p[NP * c + 1] * dt
        out_p[c, 2] = p[NP * c + 2] * dt
    rms = math.sqrt(ss / max(nw, 1.0))
    if rms > POOR_FIT_SD * sd + POOR_FIT_PEAK * peak:
        flags |= FLAG_POOR_FIT
    if not converged:
        flags |= FLAG_NOT_CONVERGED
    return k, flags, rms


@njit(parallel=True, cache=True)
def _decompose_kernel(samples, lengths, dt, mean, sd, agc_gain, s_min_ns, s_max_ns, min_snr, merge_sd, fixed_width,
                      smooth_ns, max_iter, out_p, out_k, out_flags, out_rms):
    n_rows = samples.shape[0]
    n_blocks = (n_rows + BLOCK - 1) // BLOCK
    for blk in prange(n_blocks):
        ws = scratch(samples.shape[1], out_p.shape[1])
        s_prev = -1.0
        g, var = _kernel(1.0)
        for i in range(blk * BLOCK, min(n_rows, (blk + 1) * BLOCK)):
            s_smooth = max(0.5, smooth_ns / dt[i])
            if s_smooth != s_prev:
                g, var = _kernel(s_smooth)
                s_prev = s_smooth
            k, f, rms = decompose_row(samples[i], lengths[i], dt[i], mean[i], sd[i], agc_gain[i], s_min_ns, s_max_ns,
                                      min_snr, merge_sd, fixed_width, g, var, max_iter, ws, out_p[i])
            out_k[i], out_flags[i], out_rms[i] = k, f, rms


def decompose(samples, lengths, sampling_ns, noise_mean, noise_sd, *, pulse_fwhm_ns: float | None = None,
              fixed_width: bool = False, min_snr: float = 3.0, max_echoes: int = 8, merge_sd: float = 1.0,
              max_width_factor: float = 6.0, max_iter: int = 30, agc_gain=None) -> Decomposition:
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
    agc_gain : float or (n,), the AGC gain g each waveform was divided by ((V - n0) / g + n0,
        Eq. 1, n0 = ``noise_mean``; NaN or None: 1, raw samples): the clipped test's raw values.
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
    gain = np.ones(n) if agc_gain is None else checks.gain_or_one(np.broadcast_to(np.asarray(agc_gain, float), (n,)))
    fwhm_to_sd = 1.0 / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    s_min = float(pulse_fwhm_ns) * fwhm_to_sd if pulse_fwhm_ns else 0.5 * float(np.min(dt, initial=1.0))
    s_max = max_width_factor * (s_min if pulse_fwhm_ns else 2.0 * float(np.max(dt, initial=1.0)))
    smooth_ns = 0.5 * s_min if pulse_fwhm_ns else float(np.min(dt, initial=1.0))
    out = np.full((n, int(max_echoes), 3), np.nan)
    k = np.zeros(n, np.int64)
    flags = np.zeros(n, np.int64)
    rms = np.full(n, np.nan)
    if n:
        _decompose_kernel(x, lens, dt, mean, sd, np.ascontiguousarray(gain, np.float64), s_min, s_max, float(min_snr), float(merge_sd), bool(fixed_width),
                          smooth_ns, int(max_iter), out, k, flags, rms)
    return Decomposition(out[:, :, 0], out[:, :, 1], out[:, :, 2], k.astype(np.int16), flags.astype(np.uint8), rms)
