"""The signature test: the gap read along each candidate effect's signature.

docs/method.md §(j) (the signature test). The moment gap G (:mod:`.gap`) squares every
label x feature term and averages them, so an effect that moves a few terms is diluted by
all the others, and by every statistic added. A missing effect moves the terms in a known
direction, its *signature*; the projection of the observed terms on it collects the effect's
evidence from every statistic, first echo and whole waveform alike, and no other noise.

Terms: x_k, k = (label, feature, moment), the label-pooled ``d_bar`` and ``l_bar`` of the gap
(:func:`.gap.pooled`) over the features :data:`.gap.ALL_FEATURES` (with their cell rules).
Candidate e has the signature s_e, the terms of its simulation against the base model's with
common random numbers (:func:`terms` of the two tables), at one value. Per data set ::

    T_e = s_e' V^-1 x                  V = D R D, the terms' null covariance: D the diagonal of
                                       their SDs (robust bootstrap SD, RMS over the power
                                       analysis' replicates without effect), R their bootstrap
                                       correlation over those replicates, shrunk toward none:
                                       R = (1 - lambda) R* + lambda I, lambda = SHRINKAGE
    z_e = T_e / SD*(T_e)               SD* the robust SD over the cluster bootstrap's replicates

Weighting by V^-1 rather than by the variances alone is the matched filter of correlated noise:
an effect that moves one of two correlated terms is seen against their difference, whose noise
is the smaller (by sqrt(1 - r^2)).

Without effect z_e is about N(0, c_e^2); c_e, the RMS of z_e over the replicates without
effect, never below 1 (a bootstrap that overstates the noise is kept: conservative). The test
*fires* when ``max_e |z_e| / c_e`` exceeds the ``1 - alpha / (2 m)`` quantile of Student's t with
field samples - strata degrees of freedom (two-sided, Bonferroni over the m candidates, ``alpha``
= :data:`ALPHA`). Its *margin* ``max_e |z_e| / c_e - crit`` is > 0
when it fires.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from functools import cached_property
from statistics import NormalDist

import numpy as np
import pandas as pd
from scipy.stats import t as student_t

from waveforest.diagnose.gap import ALL_FEATURES, GapData, cell_statistics, pooled
from waveforest.stats.bootstrap import robust_sd

ALPHA = 0.01
"""Family-wise false-alarm rate of the signature test over all candidates (two-sided)."""

SHRINKAGE = 0.2
"""lambda: the share of the terms' bootstrap correlation R* replaced by none (1: each term
weighted by its variance alone). The bootstrap resamples field samples; the twins' Monte Carlo
and coverage noise is only partly in R*, so it is not trusted whole (docs/validation.md)."""

_MOMENTS = ("d", "log_sd_ratio")


def terms(real: pd.DataFrame, sim: pd.DataFrame, universe: pd.Series, weights: np.ndarray | None = None, *,
          floors: dict | None = None, min_pulses: int, min_samples: int) -> tuple[pd.Series, np.ndarray | None]:
    """The label-pooled terms of ``sim`` against ``real`` (module docstring), over the features of
    :data:`.gap.ALL_FEATURES` that both tables carry.

    Returns
    -------
    point : Series
        Indexed by (label, feature, moment); terms with no valid cell are left out.
    boot : (B, K) float64 or None
        The same terms in each bootstrap replicate of ``weights`` ((B, J) over ``universe``).
    """
    features = tuple(f for f in ALL_FEATURES if f in real.columns and f in sim.columns)
    data = GapData.build(real, sim, universe, features=features, floors=floors, min_pulses=min_pulses,
                         min_samples=min_samples)
    return pooled_terms(data, cell_statistics(data), None if weights is None else cell_statistics(data, weights))


def pooled_terms(data: GapData, point: dict, boot: dict | None = None) -> tuple[pd.Series, np.ndarray | None]:
    """:func:`terms` of ``data`` from its :func:`.gap.cell_statistics` (``point``, and ``boot``
    of bootstrap weights or None)."""
    labels = pd.factorize(data.cells["species"])[1]
    keep = (data.label_members[:, :, None] & data.valid[None]).any(axis=1)  # (L, F), as gap.pooled keeps them
    index = pd.MultiIndex.from_tuples([(lab, f, m) for m in _MOMENTS for li, lab in enumerate(labels)
                                       for fi, f in enumerate(data.features) if keep[li, fi]],
                                      names=["label", "feature", "moment"])

    def both(stats: dict) -> np.ndarray:
        return np.concatenate([pooled(data, stats[m], data.valid) for m in _MOMENTS], axis=-1)

    return pd.Series(both(point), index=index), None if boot is None else both(boot)


def _centred(point: pd.Series, boot: np.ndarray, index: pd.Index) -> np.ndarray:
    """(B, K) bootstrap replicates of ``point``'s terms over ``index``, less their mean; 0 where
    a term is NaN."""
    b = pd.DataFrame(boot, columns=point.index).reindex(columns=index).to_numpy()
    return np.nan_to_num(b - np.nanmean(b, axis=0))


def critical_value(n_candidates: int, alpha: float = ALPHA, df: int | None = None) -> float:
    """The two-sided Bonferroni threshold of |z| over m candidates: the ``1 - alpha / (2 m)``
    quantile of Student's t with ``df`` degrees of freedom (field samples - strata: z is a
    studentised sum over field samples), of the standard normal without ``df``."""
    q = 1.0 - alpha / (2.0 * max(int(n_candidates), 1))
    return float(student_t.ppf(q, int(df))) if df is not None else NormalDist().inv_cdf(q)


@dataclass(frozen=True)
class SignatureTest:
    """The signature test of the module docstring.

    Attributes
    ----------
    signatures : dict name -> Series
        Each candidate's signature terms s_e.
    null_var : Series
        v_k per term (the squared diagonal of D).
    null_corr : DataFrame
        R, term x term (same index as ``null_var``).
    scale : dict name -> float
        c_e (>= 1).
    crit : float
        Threshold on ``|z_e| / c_e``.
    null_q : float
        The mean of x_k^2 / v_k over the terms of the replicates without effect (about 1):
        what each term adds to :meth:`excess` without effect.
    """

    signatures: dict
    null_var: pd.Series
    null_corr: pd.DataFrame
    scale: dict
    crit: float
    null_q: float = 1.0

    @classmethod
    def calibrate(cls, signatures: dict, off: list, alpha: float = ALPHA, df: int | None = None,
                  shrinkage: float = SHRINKAGE) -> SignatureTest:
        """The test of ``signatures`` (name -> Series of terms), its null covariance and scales
        from ``off``: the (point, boot) :func:`terms` of the replicates without effect;
        threshold :func:`critical_value` (``alpha``, ``df``); lambda = ``shrinkage``."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a term NaN in every replicate
            var = pd.concat([pd.Series(robust_sd(b) ** 2, index=p.index) for p, b in off], axis=1).mean(axis=1)
            dev = np.concatenate([_centred(p, b, var.index) for p, b in off])
        cov = dev.T @ dev
        sd = np.sqrt(np.diag(cov))
        with np.errstate(invalid="ignore", divide="ignore"):
            r = np.nan_to_num(cov / np.outer(sd, sd))
        r = (1.0 - shrinkage) * r + shrinkage * np.eye(len(r))
        np.fill_diagonal(r, 1.0)
        test = cls(signatures=signatures, null_var=var, null_corr=pd.DataFrame(r, index=var.index, columns=var.index),
                   scale=dict.fromkeys(signatures, 1.0), crit=critical_value(len(signatures), alpha, df))
        z = pd.DataFrame([test.z(p, b) for p, b in off])
        scale = {e: max(1.0, math.sqrt(float(np.nanmean(z[e] ** 2)))) if z[e].notna().any() else 1.0
                 for e in signatures}
        q = np.concatenate([test._q(p) for p, _ in off])
        return replace(test, scale=scale, null_q=float(q.mean()) if q.size else 1.0)

    def _q(self, point: pd.Series) -> np.ndarray:
        """x_k^2 / v_k of the terms of ``point`` with a null variance."""
        v = self.null_var.reindex(point.index).to_numpy()
        x = point.to_numpy()
        ok = np.isfinite(x) & (v > 0)
        return x[ok] ** 2 / v[ok]

    def excess(self, point: pd.Series) -> float:
        """The evidence of one data set's terms against its noise: sum_k (x_k^2 / v_k - null_q),
        about 0 without effect, whatever the direction of a disagreement."""
        return float(np.sum(self._q(point) - self.null_q))

    @cached_property
    def _signature_matrix(self) -> np.ndarray:
        """(K, m) the signatures over ``null_var``'s terms, NaN where a signature lacks one."""
        return pd.DataFrame(self.signatures).reindex(self.null_var.index).to_numpy()

    def project(self, point: pd.Series, boot: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """T_e of every candidate (in the order of ``signatures``) for one data set's
        :func:`terms`: (T (m,), its bootstrap replicates (B, m), whether candidate e has a
        common term (m,) bool). Terms NaN in ``point`` are left out."""
        pos = self.null_var.index.get_indexer(point.index)
        v = np.where(pos >= 0, self.null_var.to_numpy()[pos], np.nan)
        x = point.to_numpy()
        ok = np.isfinite(x) & (v > 0)
        sd = np.sqrt(v[ok])[:, None]
        r = self.null_corr.to_numpy()[np.ix_(pos[ok], pos[ok])]
        w = np.linalg.solve(r, np.nan_to_num(self._signature_matrix[pos[ok]]) / sd) / sd
        return x[ok] @ w, np.nan_to_num(boot[:, ok]) @ w, np.abs(w).sum(axis=0) > 0

    def z(self, point: pd.Series, boot: np.ndarray) -> dict:
        """z_e of every candidate for one data set's :func:`terms` (NaN: no common term)."""
        t, tb, has = self.project(point, boot)
        s = robust_sd(tb)
        with np.errstate(invalid="ignore", divide="ignore"):
            z = np.where((s > 0) & has, t / s, np.nan)
        return {e: float(z[i]) for i, e in enumerate(self.signatures)}

    def margin(self, point: pd.Series, boot: np.ndarray) -> tuple[float, str]:
        """(``max_e |z_e| / c_e - crit``, the candidate e that reaches it); > 0: the test fires."""
        return self.margin_of(self.z(point, boot))

    def margin_of(self, z: dict) -> tuple[float, str]:
        """:meth:`margin` of the z_e of :meth:`z`."""
        r = {e: abs(v) / self.scale[e] for e, v in z.items() if math.isfinite(v)}
        if not r:
            return -math.inf, ""
        best = max(r, key=r.get)
        return r[best] - self.crit, best

    def read(self, point: pd.Series, boot: np.ndarray) -> dict:
        """The test on one data set, as ``verdict.json`` records it: ``fires``, ``margin``,
        ``effect`` (the candidate of the largest ``|z| / c``), ``threshold`` (crit), and per
        candidate ``z`` and ``scale`` (c)."""
        z = self.z(point, boot)
        margin, best = self.margin_of(z)
        num = lambda x: float(x) if math.isfinite(x) else None  # noqa: E731
        return {"fires": bool(margin > 0), "margin": num(margin), "effect": best, "threshold": float(self.crit),
                "z": {e: num(v) for e, v in z.items()}, "scale": {e: float(c) for e, c in self.scale.items()}}
