"""Additive waveform noise c of Eq. 7 and its estimate from the record tail (docs/method.md §(c), e).

The model's noise is Gaussian with the dataset's mean and SD, independent between samples,
added at the output sampling rate. The ``noise_autocorr`` effect (src/waveforest/effects.py)
makes it a stationary AR(1) process with the same marginal SD:
``e[0] = z[0]``, ``e[k] = phi e[k-1] + sqrt(1 - phi^2) z[k]`` (z standard normal), scaled by SD.

The estimate (docs/method.md §(e)): the last ``tail`` samples of each waveform (50 by default) hold
noise only; the mean and SD of all of them pooled give c-bar and its SD. Recorded samples are
integers (8-bit digitiser), so the recorded SD includes the rounding variance 1/12 DN^2;
:attr:`NoiseStats.sd_analog` removes it, which is the SD to give the signal model (that rounds
again).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from numba import njit, prange

import waveforest.sensor.checks as checks
from waveforest.sensor.params import INTEGER_TOL, QUANTISATION_VAR


@njit(parallel=True, cache=True, nogil=True)
def _ar1_kernel(z, phi, out):
    """Stationary AR(1) rows of unit marginal variance from standard normal rows ``z``."""
    c = math.sqrt(1.0 - phi * phi)
    n, m = z.shape
    for i in prange(n):
        if m == 0:
            continue
        e = z[i, 0]
        out[i, 0] = e
        for k in range(1, m):
            e = phi * e + c * z[i, k]
            out[i, k] = e


def ar1(z: np.ndarray, phi: float) -> np.ndarray:
    """Stationary AR(1) noise rows with coefficient ``phi`` and unit marginal SD.

    Parameters
    ----------
    z : (n, m) float, independent standard normal draws.
    phi : float in (-1, 1), lag-1 autocorrelation.

    Returns
    -------
    (n, m) float64.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError(f"ar1: z must be 2-D, got shape {z.shape}")
    if not (-1.0 < phi < 1.0):
        raise ValueError(f"ar1: the AR(1) coefficient must lie in (-1, 1), got {phi}")
    if phi == 0.0:
        return z.copy()
    out = np.empty_like(z)
    _ar1_kernel(np.ascontiguousarray(z), float(phi), out)
    return out


def gaussian_noise(rng: np.random.Generator, shape: tuple[int, int], mean, sd, autocorr: float = 0.0) -> np.ndarray:
    """Noise c (DN) of shape (n, m): mean + sd * AR(1)(autocorr) of standard normal draws.

    ``mean`` and ``sd`` are scalars or (n,) arrays. One draw of ``rng.standard_normal(shape)``.
    """
    n = shape[0]
    mean = checks.per_pulse(mean, n, "noise_mean")
    sd = checks.per_pulse(sd, n, "noise_sd", nonnegative=True)
    z = rng.standard_normal(shape)
    e = ar1(z, autocorr) if autocorr != 0.0 else z
    return mean[:, None] + sd[:, None] * e


@dataclass(frozen=True)
class NoiseStats:
    """Noise estimate from waveform tails (docs/method.md §(e)).

    mean : float, DN (c-bar).  sd : float, DN, SD of the recorded tail samples.
    sd_analog : float, DN, sd with the rounding variance removed when the samples are integers.
    n_samples : int, tail samples used.  n_pulses : int, waveforms used.
    lag1 : float, lag-1 autocorrelation of the tail noise (0 for white noise).
    quantised : bool, the tail samples are integers.
    """

    mean: float
    sd: float
    sd_analog: float
    n_samples: int
    n_pulses: int
    lag1: float
    quantised: bool

    def to_dict(self) -> dict:
        return asdict(self)


def tail_samples(samples, lengths, tail: int) -> tuple[np.ndarray, np.ndarray]:
    """The last ``tail`` valid samples of each row, (n, tail) float64 NaN-padded, and a mask.

    Rows shorter than ``tail`` give all their samples.
    """
    x, lens = checks.waveforms(samples, lengths)
    if tail < 1:
        raise ValueError(f"tail must be >= 1, got {tail}")
    n = x.shape[0]
    cols = lens[:, None] - tail + np.arange(tail)[None, :]
    ok = cols >= 0
    vals = np.full((n, tail), np.nan)
    if n:
        rows = np.broadcast_to(np.arange(n)[:, None], cols.shape)
        vals[ok] = x[rows[ok], cols[ok]]
    return vals, ok


def noise_stats(samples, lengths=None, tail: int = 50, *, gain=None, n0: float | None = None) -> NoiseStats:
    """Noise mean and SD from the last ``tail`` samples of each waveform (docs/method.md §(e)).

    Parameters
    ----------
    samples : (n, n_s) DN; lengths : (n,) valid lengths or None.
    tail : int, samples per waveform (config ``calibrate.noise_tail``).
    gain, n0 : optional (n,) AGC gains and the level n0 used by an AGC normalisation
        (Eq. 1, ``V_norm = (V - n0)/g + n0``); the tails are mapped back to recorded values
        ``(V_norm - n0) g + n0`` first, because the AGC does not change the noise.

    Returns
    -------
    NoiseStats
    """
    vals, ok = tail_samples(samples, lengths, tail)
    if gain is not None:
        if n0 is None:
            raise ValueError("noise_stats: n0 is required with gain")
        g = checks.per_pulse(gain, vals.shape[0], "gain", positive=True)
        vals = (vals - n0) * g[:, None] + n0
    v = vals[ok]
    if v.size < 2:
        raise ValueError(f"noise_stats: fewer than 2 tail samples (n = {v.size})")
    mean = float(v.mean())
    sd = float(v.std(ddof=1))
    quantised = bool(np.all(np.abs(v - np.round(v)) < INTEGER_TOL))
    sd_analog = math.sqrt(max(sd**2 - QUANTISATION_VAR, 0.0)) if quantised else sd
    # lag-1 autocorrelation of the tails, deviations from each row's own tail mean
    filled = np.where(ok, vals, 0.0)
    row_mean = filled.sum(axis=1) / np.maximum(ok.sum(axis=1), 1)
    dev = np.where(ok, filled - row_mean[:, None], 0.0)
    pair = ok[:, :-1] & ok[:, 1:]
    den = float(np.sum(dev**2))
    lag1 = float(np.sum(np.where(pair, dev[:, :-1] * dev[:, 1:], 0.0)) / den) if den > 0 else 0.0
    n_pulses = int(np.count_nonzero(ok.any(axis=1)))
    return NoiseStats(mean, sd, sd_analog, int(v.size), n_pulses, lag1, quantised)
