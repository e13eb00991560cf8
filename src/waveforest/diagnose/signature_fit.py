"""The fit along a signature: the value at which a candidate's signature no longer sees the gap.

docs/method.md §(j) (the fit along the signature). The search's gap G (:mod:`.gap`) weighs
every term alike and is fitted on half the field samples; the signature test
(:mod:`.signature_test`) reads all samples along each candidate's signature, through the
terms' null covariance, and can see an effect whose half-sample gap curve is too noisy to fit.
This module fits a candidate along its signature instead:

* the terms x(u) of the real data against the model with candidate e at each grid value u
  (all field samples, common random numbers: the search's simulations) give the signature
  test's statistic T_e(u) = s_e' V^-1 x(u) (:meth:`.signature_test.SignatureTest.project`).
  At off it is the data's T_e; it passes 0 where the model holds as much of e as the data do;
* the fitted value is that zero crossing, linear in u between grid values, the crossing
  nearest off (:func:`zero_crossings`); its interval the percentiles of the crossings of the
  same cluster-bootstrap replicates, a replicate without crossing counted at the end of the
  range where its |T_e| is smallest;
* the model *explains the evidence* when, at the fitted value, the signature test no longer
  fires and at least :data:`EXPLAINED_SHARE` of the terms' evidence against their noise
  (:meth:`.signature_test.SignatureTest.excess`, in every direction, not only along the
  signatures) is gone: the terms there are linear in u between the neighbouring grid values
  (common random numbers: they move smoothly with u; :func:`terms_at`). A disagreement
  that no candidate makes can still lean on one signature; its evidence then stays.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from waveforest.diagnose.signature_test import SignatureTest

EXPLAINED_SHARE = 0.5
"""The least share of the terms' excess evidence that a fit along a signature must remove."""


def common_terms(points: list[pd.Series], boots: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, pd.Index]:
    """The terms of several models over the terms valid in all of them.

    Parameters
    ----------
    points : list of k Series
        :func:`.signature_test.terms` point values, one per model.
    boots : list of k (B, K_i) float64
        Their bootstrap replicates (the same weights).

    Returns
    -------
    x : (k, K) float64
    xb : (k, B, K) float64
    index : Index of the K terms (label, feature, moment)
    """
    index = points[0].index
    for p in points[1:]:
        index = index.intersection(p.index, sort=False)
    finite = np.all([np.isfinite(p.reindex(index).to_numpy()) for p in points], axis=0)
    index = index[finite]
    x = np.stack([p.reindex(index).to_numpy() for p in points])
    xb = np.stack([pd.DataFrame(b, columns=p.index).reindex(columns=index).to_numpy() for p, b in zip(points, boots)])
    return x, xb, index


def zero_crossings(u: np.ndarray, t: np.ndarray, u_off: float) -> np.ndarray:
    """Where each curve ``t`` (B, k) over the sorted grid ``u`` (k,) crosses 0, linear between
    grid values: the crossing nearest ``u_off`` (the first one going away from off). (B,);
    NaN for a curve without crossing."""
    u, t = np.asarray(u, np.float64), np.atleast_2d(np.asarray(t, np.float64))
    ta, tb = t[:, :-1], t[:, 1:]
    cross = (np.sign(ta) != np.sign(tb)) | (ta == 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        frac = np.where(ta != tb, ta / (ta - tb), 0.0)
    root = u[:-1] + np.clip(frac, 0.0, 1.0) * np.diff(u)
    dist = np.where(cross & np.isfinite(root), np.abs(root - u_off), np.inf)
    j = np.argmin(dist, axis=1)
    out = root[np.arange(len(t)), j]
    return np.where(np.isfinite(dist[np.arange(len(t)), j]), out, np.nan)


def fit_along(test: SignatureTest, name: str, u: np.ndarray, x: np.ndarray, xb: np.ndarray, index: pd.Index,
              u_off: float) -> tuple[float, np.ndarray]:
    """The fit of candidate ``name`` along its signature (module docstring).

    Parameters
    ----------
    test : SignatureTest
    u : (k,) float64
        Sorted grid values of the candidate (search coordinate), off among them.
    x, xb, index
        :func:`common_terms` of the model at each of them.
    u_off : float
        The candidate's off value.

    Returns
    -------
    u_hat : float
        The fitted value; NaN when T_e does not cross 0 on the grid.
    u_boot : (B,) float64
        The bootstrap replicates' crossings, those without one at the end of the grid where
        their |T_e| is smallest.
    """
    e = list(test.signatures).index(name)
    proj = [test.project(pd.Series(x[i], index=index), xb[i]) for i in range(len(u))]
    t = np.array([p[0][e] for p in proj])
    tb = np.stack([p[1][:, e] for p in proj], axis=1)  # (B, k)
    u_hat = float(zero_crossings(u, t[None, :], u_off)[0])
    u_boot = zero_crossings(u, tb, u_off)
    end = np.where(np.abs(tb[:, 0]) < np.abs(tb[:, -1]), u[0], u[-1])
    return u_hat, np.where(np.isfinite(u_boot), u_boot, end)


def terms_at(u_hat: float, u: np.ndarray, x: np.ndarray, xb: np.ndarray, index: pd.Index) -> tuple[pd.Series, np.ndarray]:
    """The terms (point, (B, K) replicates) at ``u_hat``, linear in u between the neighbouring
    grid values of ``u`` (k,) (:func:`common_terms`' ``x``, ``xb``, ``index``)."""
    j = int(np.clip(np.searchsorted(u, u_hat) - 1, 0, len(u) - 2))
    f = float(np.clip((u_hat - u[j]) / (u[j + 1] - u[j]), 0.0, 1.0))
    return pd.Series((1 - f) * x[j] + f * x[j + 1], index=index), (1 - f) * xb[j] + f * xb[j + 1]


def explained(test: SignatureTest, before: pd.Series, after: tuple[pd.Series, np.ndarray]) -> tuple[bool, dict, float]:
    """Whether the terms ``after`` (point, replicates) explain the evidence of the terms ``before``
    (module docstring): (explained, the test's reading after, the share of the excess removed)."""
    reading = test.read(*after)
    ex0, ex1 = test.excess(before), test.excess(after[0])
    share = 1.0 - ex1 / ex0 if ex0 > 0 else 0.0
    return bool(not reading["fires"] and share >= EXPLAINED_SHARE), reading, share
