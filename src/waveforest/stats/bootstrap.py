"""Cluster-bootstrap statistics: stratified resampling weights, robust SEs and intervals.

Generic: a *universe* is a Series ``cluster id -> stratum`` (J clusters); a bootstrap of B
replicates is a (B, J) matrix of multiplicities, so any statistic that is a function of
per-cluster sums is bootstrapped by a matrix product. Replicates of a statistic are arrays
of shape (B, ...) (NaN where a replicate is degenerate).

* :func:`bootstrap_weights` — multiplicities of the rescaling bootstrap (Rao & Wu 1988,
  m = J_s - 1 per stratum);
* :func:`robust_sd` — SE* = IQR / 1.349 of the replicates (robust to degenerate replicates);
* :func:`nanquantile0` — ``np.nanquantile`` over axis 0 without a Python loop over columns;
* :func:`wald_interval` — ``estimate -+ t(1 - alpha/2, df) * SE*``;
* :func:`recentred_interval` — percentile interval recentred on the estimate,
  ``[estimate + q(alpha/2) - median, estimate + q(1 - alpha/2) - median]``;
* :func:`cluster_df` — degrees of freedom of a pooled statistic, clusters - strata.

Used by the gap of :mod:`waveforest.diagnose.gap` (docs/method.md §(j)). Errors: ValueError
for ``n_boot < 1``.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from waveforest.rng import named_generator

DEFAULT_ALPHA = 0.05
"""Two-sided level of every interval (95 % intervals)."""


def bootstrap_weights(universe: pd.Series, n_boot: int, seed) -> np.ndarray:
    """Multiplicities of a cluster bootstrap stratified by species.

    Within each species of J_s samples, J_s - 1 samples are drawn with replacement (the
    rescaling bootstrap of Rao & Wu 1988 with m = J_s - 1): the plain bootstrap's variance of a
    mean is biased low by (J_s - 1) / J_s, which matters with the few field samples per
    species of a campaign (intervals of d then have their nominal coverage).

    Parameters
    ----------
    universe : Series
        ``sample_id -> species`` (:func:`sample_universe`), J samples.
    n_boot : int
        Replicates B.
    seed : int
        Seed of the draws (the named stream ``bootstrap``).

    Returns
    -------
    (B, J) float64
        How many times each sample enters each replicate; each species' entries sum to J_s - 1.
    """
    if n_boot < 1:
        raise ValueError(f"n_boot must be >= 1, got {n_boot}")
    rng = named_generator("bootstrap", seed)
    species = universe.to_numpy()
    w = np.zeros((n_boot, len(species)))
    for sp in np.unique(species):
        idx = np.flatnonzero(species == sp)
        m = max(len(idx) - 1, 1)
        w[:, idx] = rng.multinomial(m, np.full(len(idx), 1.0 / len(idx)), size=n_boot)
    return w



def recentred_interval(estimate: float, replicates: np.ndarray, alpha: float = DEFAULT_ALPHA) -> tuple[float, float]:
    """Bootstrap percentile interval of ``replicates`` shifted so its centre is ``estimate``.

    ``[estimate + q(alpha/2) - median, estimate + q(1 - alpha/2) - median]`` of the finite
    replicates: the bootstrap's shape, without the upward bias that resampling adds to
    squared statistics (docs/method.md §(j), the gap). The median, not the mean, is the centre: a few
    replicates with a near-degenerate cell have huge squared terms (:func:`robust_sd`).
    """
    r = np.asarray(replicates, dtype=np.float64)
    r = r[np.isfinite(r)]
    if r.size < 2:
        return (np.nan, np.nan)
    lo, m, hi = np.quantile(r, [alpha / 2, 0.5, 1 - alpha / 2])
    return (float(estimate + lo - m), float(estimate + hi - m))


def wald_interval(estimate: np.ndarray, replicates: np.ndarray, df, alpha: float = DEFAULT_ALPHA) -> np.ndarray:
    """``estimate -+ t(1 - alpha/2, df) * SE*``, SE* the (robust, :func:`robust_sd`) SD of the
    bootstrap replicates.

    Used for nearly unbiased, nearly symmetric statistics (d, l, gap differences); its
    coverage with few clusters is checked in tests/test_diagnose_gap.py.

    Parameters
    ----------
    estimate : (...) float64
    replicates : (B, ...) float64
    df : int or (...) int
        Degrees of freedom: field samples of the cell minus 1.

    Returns
    -------
    (2, ...) float64
        Lower and upper bounds.
    """
    from scipy.stats import t as student_t

    half = student_t.ppf(1 - alpha / 2, df) * robust_sd(replicates)
    return np.stack([estimate - half, estimate + half])


IQR_PER_SD = 1.3489795003921634
"""Interquartile range of a normal distribution in SDs (2 * Phi^-1(0.75))."""


def robust_sd(replicates: np.ndarray) -> np.ndarray:
    """SD of bootstrap replicates estimated as IQR / 1.349 (over axis 0, ignoring NaN).

    A replicate that draws one or two field samples into a cell can give a near-zero pooled
    SD and so a huge d (and d^2), which inflates the plain SD of the replicates without
    bound. The IQR ignores those tails and equals the SD for normal replicates, which d, l
    and gap differences nearly are.

    Parameters
    ----------
    replicates : (B, ...) float64

    Returns
    -------
    (...) float64; NaN where fewer than 2 replicates are finite.
    """
    r = np.asarray(replicates, dtype=np.float64)
    q1, q3 = nanquantile0(r, (0.25, 0.75))
    out = (q3 - q1) / IQR_PER_SD
    return np.where(np.sum(np.isfinite(r), axis=0) >= 2, out, np.nan)


def nanquantile0(x: np.ndarray, q) -> np.ndarray:
    """``np.nanquantile(x, q, axis=0)`` (linear method, bit for bit) in one sort of ``x``.

    NumPy's ``nanquantile`` over an axis loops in Python over every slice that holds a NaN;
    this sorts once (NaN last) and interpolates each column at ``q (n - 1)``, n its count of
    non-NaN values, with NumPy's own lerp.

    Parameters
    ----------
    x : (B, ...) float64
    q : sequence of float in [0, 1]

    Returns
    -------
    (len(q), ...) float64; NaN where a column has no non-NaN value.
    """
    s = np.sort(np.asarray(x, dtype=np.float64), axis=0)
    n = np.sum(~np.isnan(s), axis=0)
    out = np.full((len(q),) + s.shape[1:], np.nan)
    if s.shape[0] == 0:
        return out
    for i, qi in enumerate(q):
        vi = (n - 1) * qi  # NumPy's virtual index of the linear method
        below = np.floor(vi)
        at_end = vi >= n - 1
        lo = np.where(at_end, n - 1, below).astype(np.intp)
        hi = np.where(at_end, n - 1, lo + 1)
        t = np.where(at_end, 0.0, vi - below)
        a = np.take_along_axis(s, np.maximum(lo, 0)[None], axis=0)[0]
        b = np.take_along_axis(s, np.maximum(hi, 0)[None], axis=0)[0]
        with np.errstate(invalid="ignore"):  # inf - inf: NaN, as NumPy's
            diff = b - a
            v = np.where(t >= 0.5, b - diff * (1.0 - t), a + diff * t)
        out[i] = np.where(n > 0, v, np.nan)
    return out


def cluster_df(universe: pd.Series) -> int:
    """Degrees of freedom of a statistic pooled over all clusters: clusters - strata (>= 1)."""
    return max(len(universe) - universe.nunique(), 1)
