"""The before/after comparison: two simulations against the same real data, paired.

Both simulations are reduced with one sample universe (:func:`.gap.sample_universe`) and
one set of cluster-bootstrap weights (:func:`waveforest.stats.bootstrap.bootstrap_weights`),
so every replicate resamples the same field samples for the real data and both
simulations (a paired cluster bootstrap), and both gaps average the same cells (valid in
both). The reduction ``R = G_base - G_new`` (squared pooled SDs) gets a Wald interval
``R -+ t * SE*`` with samples - species degrees of freedom (per cell: samples - 1); each
gap a recentred percentile interval clipped at 0 (:func:`.gap.gap_interval`; docs/method.md
§(j), the gap).

* :func:`paired_reduction` — the total reduction (:class:`Reduction`);
* :func:`before_after` — the table per cell, per feature and in total (``gap_before_after.csv``).

Errors: :class:`waveforest.errors.WaveforestError` when no cell is valid in both.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pandas as pd

from waveforest.diagnose.gap import (
    GapData,
    cell_statistics,
    gap_interval,
    masked_floor,
    masked_gap,
    sample_universe,
    total_gap,
    total_noise_floor,
    wasserstein_cells,
)
from waveforest.errors import WaveforestError
from waveforest.stats.bootstrap import (
    DEFAULT_ALPHA,
    bootstrap_weights,
    cluster_df,
    wald_interval,
)


@dataclass
class Reduction:
    """Paired comparison of two simulations against the same real data (same bootstrap).

    Attributes
    ----------
    gap_base, gap_new : float
        Total moment gaps G of the baseline and the new simulation.
    noise_base : float
        Noise floor of the baseline.
    reduction : float
        ``gap_base - gap_new`` (> 0: the new simulation agrees better).
    ci_low, ci_high : float
        Interval of the reduction, ``reduction -+ t * SE*`` with the paired bootstrap's
        standard error (same resamples for both) and samples - species degrees of freedom.
    relative : float
        ``reduction / (gap_base - noise_base)``: the share of the baseline's excess gap
        removed; NaN when the baseline has no excess.
    replicates : (B,) float64
        Bootstrap replicates of the reduction.
    """

    gap_base: float
    gap_new: float
    noise_base: float
    reduction: float
    ci_low: float
    ci_high: float
    relative: float
    replicates: np.ndarray


def paired_reduction(real: pd.DataFrame, sim_base: pd.DataFrame, sim_new: pd.DataFrame, *, n_boot: int = 200,
                     seed=0, alpha: float = DEFAULT_ALPHA, universe: pd.Series | None = None, **build_kw) -> Reduction:
    """How much ``sim_new`` reduces the gap of ``sim_base``, with a paired cluster bootstrap.

    Both gaps average the same cells (valid in both) and every replicate resamples the same
    field samples for the real data and both simulations.
    """
    universe, a, b, valid = _paired(real, sim_base, sim_new, universe, build_kw)
    w = bootstrap_weights(universe, n_boot, seed)
    ga, gb = total_gap(a, valid=valid), total_gap(b, valid=valid)
    reps = total_gap(a, w, valid) - total_gap(b, w, valid)
    lo, hi = wald_interval(ga - gb, reps, cluster_df(universe), alpha)
    fl = total_noise_floor(a, w, valid)
    excess = ga - fl
    rel = (ga - gb) / excess if excess > 0 else np.nan
    return Reduction(gap_base=ga, gap_new=gb, noise_base=fl, reduction=ga - gb, ci_low=lo, ci_high=hi,
                     relative=float(rel), replicates=reps)


def before_after(real: pd.DataFrame, sim_before: pd.DataFrame, sim_after: pd.DataFrame, *, n_boot: int = 200,
                 seed=0, alpha: float = DEFAULT_ALPHA, wasserstein: bool = True, **build_kw) -> pd.DataFrame:
    """The gap of two simulations (base and extended model) against the same real data.

    One paired cluster bootstrap (the same resampled field samples for the real data and
    both simulations) gives the interval of each gap and of its reduction; both gaps average
    the same cells (valid in both).

    Parameters
    ----------
    real, sim_before, sim_after : DataFrame
        Feature tables (dataset, species, sample_id, features).
    n_boot, seed, alpha
        Bootstrap replicates, seed and interval level.
    wasserstein : bool
        Also report W1 / pooled SD per cell (before and after).
    **build_kw
        :meth:`GapData.build` settings (features, floors, min_pulses, min_samples).

    Returns
    -------
    DataFrame
        One row per dataset x species x feature (``level = cell``), per feature (``level =
        feature``, dataset and species empty) and one ``level = total`` row, with: n_cells,
        gap_before, before_ci_low, before_ci_high, gap_after, after_ci_low, after_ci_high
        (bounds >= 0), noise_floor (of the base model), reduction, reduction_ci_low, reduction_ci_high,
        relative_reduction (share of the base model's excess gap removed); cell rows also
        d_before, d_after, log_sd_ratio_before, log_sd_ratio_after, w1_before, w1_after,
        n_real, n_sim_before, n_sim_after, mean_real, mean_before, mean_after.
        Gaps are moment gaps (squared pooled SDs; a cell's gap is its d^2 + l^2).
    """
    universe, a, b, valid = _paired(real, sim_before, sim_after, None, build_kw)
    if not valid.any():
        raise WaveforestError("gap: no cell has enough real and simulated pulses to compare")
    w = bootstrap_weights(universe, n_boot, seed)
    pair = _PairedTerms.of(a, b, w, alpha)
    pa_, pb_ = pair.point
    w1a = w1b = np.full(valid.shape, np.nan)
    if wasserstein:
        q = [alpha / 2, 1 - alpha / 2]
        w1a, _ = wasserstein_cells(_with_valid(a, valid), pa_["pooled_sd"], w[:0], q)
        w1b, _ = wasserstein_cells(_with_valid(b, valid), pb_["pooled_sd"], w[:0], q)
    df_cell = np.maximum((a.n[0] > 0).sum(axis=-1) - 1, 1)
    df_all = cluster_df(universe)
    rows = []
    for c, (ds, sp) in enumerate(a.cells.itertuples(index=False)):
        for k, f in enumerate(a.features):
            if not valid[c, k]:
                continue
            mask = np.zeros_like(valid)
            mask[c, k] = True
            rows.append({"level": "cell", "dataset": ds, "species": sp, "feature": f,
                         **pair.summarise(mask, df_cell[c, k]),
                         "d_before": pa_["d"][c, k], "d_after": pb_["d"][c, k],
                         "log_sd_ratio_before": pa_["log_sd_ratio"][c, k],
                         "log_sd_ratio_after": pb_["log_sd_ratio"][c, k],
                         "w1_before": w1a[c, k], "w1_after": w1b[c, k],
                         "n_real": int(pa_["n_real"][c, k]), "n_sim_before": int(pa_["n_sim"][c, k]),
                         "n_sim_after": int(pb_["n_sim"][c, k]), "mean_real": pa_["mean_real"][c, k],
                         "mean_before": pa_["mean_sim"][c, k], "mean_after": pb_["mean_sim"][c, k]})
    for k, f in enumerate(a.features):
        mask = valid & (np.arange(len(a.features)) == k)[None, :]
        if mask.any():
            rows.append({"level": "feature", "dataset": "", "species": "", "feature": f,
                         **pair.summarise(mask, df_all)})
    rows.append({"level": "total", "dataset": "", "species": "", "feature": "total",
                 **pair.summarise(valid, df_all)})
    return pd.DataFrame(rows)


def _paired(real: pd.DataFrame, sim_a: pd.DataFrame, sim_b: pd.DataFrame, universe: pd.Series | None,
            build_kw: dict) -> tuple[pd.Series, GapData, GapData, np.ndarray]:
    """(universe, gap data of a, gap data of b, cells valid in both) on one sample universe."""
    if universe is None:
        universe = sample_universe(real, sim_a, sim_b)
    a = GapData.build(real, sim_a, universe, **build_kw)
    b = GapData.build(real, sim_b, universe, **build_kw)
    return universe, a, b, a.valid & b.valid


@dataclass
class _PairedTerms:
    """Cell statistics of two simulations (point and bootstrap) against the same real data."""

    data: GapData
    point: tuple[dict, dict]
    replicates: tuple[dict, dict]
    alpha: float

    @classmethod
    def of(cls, a: GapData, b: GapData, weights: np.ndarray, alpha: float) -> _PairedTerms:
        return cls(data=a, point=(cell_statistics(a), cell_statistics(b)),
                   replicates=(cell_statistics(a, weights), cell_statistics(b, weights)), alpha=alpha)

    def summarise(self, mask: np.ndarray, df) -> dict:
        """Gaps before and after, their intervals and the reduction, over the cells of ``mask``."""
        (pa_, pb_), (ra, rb), alpha = self.point, self.replicates, self.alpha
        ga, gb = masked_gap(self.data, pa_, mask), masked_gap(self.data, pb_, mask)
        reps_a, reps_b = masked_gap(self.data, ra, mask), masked_gap(self.data, rb, mask)
        fl = masked_floor(self.data, ra, mask)
        lo_a, hi_a = gap_interval(ga, reps_a, alpha)
        lo_b, hi_b = gap_interval(gb, reps_b, alpha)
        r_lo, r_hi = wald_interval(ga - gb, reps_a - reps_b, df, alpha)
        excess = ga - fl
        return {"n_cells": int(mask.sum()), "gap_before": ga, "before_ci_low": lo_a, "before_ci_high": hi_a,
                "gap_after": gb, "after_ci_low": lo_b, "after_ci_high": hi_b, "noise_floor": fl,
                "reduction": ga - gb, "reduction_ci_low": float(r_lo), "reduction_ci_high": float(r_hi),
                "relative_reduction": (ga - gb) / excess if excess > 0 else np.nan}


def _with_valid(data: GapData, valid: np.ndarray) -> GapData:
    """``data`` with another validity mask (a shallow copy)."""

    return replace(data, valid=valid)
