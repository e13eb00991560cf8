"""Slow, obviously correct NumPy/Python references for the kernels of waveforest.campaign."""

from __future__ import annotations

import numpy as np


def agc_loop_reference(t_s, a0_dn, strip, z_bg, z_jit, p, lo, hi, saturation=0.0, floor=1.0):
    """The AGC loop of :mod:`waveforest.campaign.agc_loop`, one pulse at a time."""
    n = len(t_s)
    agc, gain, obs = np.zeros(n), np.zeros(n), np.zeros(n)
    x = g = 0.0
    for i in range(n):
        if i == 0 or strip[i] != strip[i - 1]:
            x = p.bg_sd * z_bg[i]
            g = p.bg_mean + x
        else:
            dt = t_s[i] - t_s[i - 1]
            r = np.exp(-dt / p.bg_tau_s)
            x = x * r + p.bg_sd * np.sqrt(1 - r * r) * z_bg[i]
            target = p.bg_mean + x
            g = target + (g - target) * np.exp(-dt / p.loop_tau_s)
        v = min(max(np.rint(g + p.jitter_sd * z_jit[i]), lo), hi)
        agc[i] = v
        gain[i] = 1 + (v - p.law_a) * p.law_b
        a = gain[i] * a0_dn[i]
        if saturation > 0:
            a = saturation * np.tanh(a / saturation)
        obs[i] = a
        g -= p.loop_gain * np.log(max(a, floor) / p.setpoint_dn)
    return agc, gain, obs


def dr_cfd_reference(x, fraction, delay, arm, dead, search, pre, post, max_echoes):
    """The DR discriminator of :mod:`waveforest.campaign.dr_cfd` on one signal, bins as integers."""
    x = np.where(np.abs(x) < 1e-9, 0.0, np.asarray(x, dtype=np.float64))
    n = len(x)
    xd = np.concatenate([np.zeros(delay), x[:-delay]]) if delay < n else np.zeros(n)
    y = xd - fraction * x
    pos, amp = [], []
    allowed, m = 1, 1
    while m < n and len(pos) < max_echoes:
        if m >= allowed and x[m] >= arm:
            ks = [k for k in range(max(allowed, m - delay, 1), min(n, m + search)) if y[k - 1] < 0 <= y[k]]
            if not ks:
                m = min(n, m + search)
                continue
            k = ks[0]
            pos.append(k - 1 + (-y[k - 1]) / (y[k] - y[k - 1]))
            amp.append(x[max(0, k - pre):min(n, k + post + 1)].max())
            allowed = k + dead
            m = k + 1
        else:
            m += 1
    return np.array(pos), np.array(amp)


def sample_reference(analog, pos0, step, n_samples):
    """Linear interpolation of each row at pos0 + k step (index units), zero outside."""
    out = np.zeros((analog.shape[0], n_samples))
    for p in range(analog.shape[0]):
        if not np.isfinite(pos0[p]):
            continue
        u = pos0[p] + step * np.arange(n_samples)
        inside = (u >= 0) & (u <= analog.shape[1] - 1)
        out[p, inside] = np.interp(u[inside], np.arange(analog.shape[1]), analog[p])
    return out
