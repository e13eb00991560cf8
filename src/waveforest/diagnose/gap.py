"""The gap: a documented measure of disagreement between real and simulated features.

docs/method.md §(j) (the gap). This module computes the gap of one simulation against the
real data (:func:`gap_report`, :func:`total_gap`); the paired comparison of two simulations
is :mod:`.before_after`, the generic bootstrap statistics :mod:`waveforest.stats.bootstrap`.
Errors: :class:`waveforest.errors.WaveforestError` for missing columns, a sample in two
species, simulated samples outside the universe, or no valid cell.

A *cell* is one dataset x species (x stratum: feature tables may carry a ``stratum`` column,
e.g. "below crown", which splits a species' pulses into cells labelled "birch below crown";
the bootstrap still resamples the species' samples with all their pulses); in it, each
feature f (the first echo's, docs/method.md §(h): H, Npeaks, Apeak, FWHM, E, and the whole
waveform's, :mod:`.waveform`: energy shares by height, below the first echo, the last return)
has real values x (n_r pulses) and simulated values y (n_s pulses).

Per cell and feature
--------------------
::

    s_p = sqrt(((n_r - 1) s_r^2 + (n_s - 1) s_s^2) / (n_r + n_s - 2)),  floored at floor_f
    d   = (mean(y) - mean(x)) / s_p               standardised mean difference
    l   = ln(max(s_s, floor_f) / max(s_r, floor_f))   log SD ratio
    w   = W1(y, x) / s_p                          Wasserstein-1 distance in pooled SDs

``floor_f`` (:data:`FEATURE_SD_FLOOR`) is the feature's measurement resolution: the SD that
rounding alone would give. It keeps a degenerate feature (Npeaks is often 1 for every
pulse) from dividing by zero and from turning a few-hundredths difference into a huge d.

Total
-----
A missing physical effect moves a species' features the same way in every dataset, while
sampling noise does not. So the cells of one label (species and stratum) are pooled over the
datasets before squaring: ``d_bar`` and ``l_bar`` are the means of d and l over the label's
valid cells of that feature (the datasets weighted equally). The *moment gap* ::

    G = mean over labels and features of (d_bar^2 + l_bar^2)

in squared pooled SDs: a shift of k SDs of one label's feature in all of D datasets adds
k^2 / K (K label x feature terms), the same shift in one dataset only k^2 / (D^2 K), and
shifts of opposite sign cancel. It is smooth in the model parameters (a good 1-D search
objective) and computable from per-sample sums, so its bootstrap is a matrix product. Per
feature, the same mean over the labels of that feature; restricted to one cell, G is that
cell's d^2 + l^2. ``w`` is reported beside it (shape differences that moments miss, e.g. the
H histogram near the ground) but does not enter G.

Noise
-----
Pulses of one field sample see the same plant and are correlated, so every bootstrap here
resamples *field samples* (clusters), stratified by species, and takes each drawn sample's
real and simulated pulses together (a paired cluster bootstrap). Even a perfect model has
E[d_bar^2] = Var(d_bar) > 0: the *noise floor* ``F = mean of (Var*(d_bar) + Var*(l_bar))``
(bootstrap variances, from interquartile ranges: :func:`waveforest.stats.bootstrap.robust_sd`)
is the gap expected from sampling noise alone (pooling D datasets divides it by up to D;
less where the datasets share field samples), and the *excess gap* is ``G - F``. On the
study's own design the bootstrap can misjudge that expectation (few field samples per cell,
skewed replicates of d and l: on the model's own twins G is 0.5-0.8 F on the smoke study's
campaigns, 1.0 F at the paper's scale on two datasets; docs/validation.md, Diagnose: the noise
floor), so F
carries a factor ``floor_scale`` (:meth:`GapData.build`) that the diagnosis calibrates on
pseudo-real data without effect (:func:`.power.floor_calibration`): the mean G over its mean F. The gap is
*significant* when the lower bound of the excess gap's interval is above 0. Intervals of G are bootstrap percentile intervals
recentred on the estimate (G + quantiles of G* - median G*): the bootstrap adds its own
noise to d*, shifting G* upwards by about F; recentring removes that shift and keeps the
skewness of a sum of squares. G >= 0, so its bounds are clipped at 0 (:func:`gap_interval`);
the excess gap's interval is G's minus F (its lower bound >= -F, negative when G's reaches
below F). Intervals of d and l are ``estimate -+ t * SE*`` (bootstrap
standard error, Student t with samples - 1 degrees of freedom), as are those of a
difference of two gaps (paired reductions; samples - species degrees of freedom); those of w
are percentile intervals (descriptive only).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import pandas as pd

from waveforest.diagnose.waveform import WAVEFORM_FEATURES, WAVEFORM_SD_FLOOR
from waveforest.errors import WaveforestError
from waveforest.stats.bootstrap import (
    DEFAULT_ALPHA,
    bootstrap_weights,
    recentred_interval,
    robust_sd,
    wald_interval,
)

FEATURES: tuple[str, ...] = ("H", "Npeaks", "Apeak", "FWHM", "E")
"""First-echo features (docs/method.md §(h)), in report order."""

ALL_FEATURES: tuple[str, ...] = FEATURES + WAVEFORM_FEATURES
"""The first echo's features and the whole waveform's (:mod:`.waveform`)."""

DEFAULT_FEATURES: tuple[str, ...] = FEATURES
"""Features compared by default (``diagnose.features``): the first echo's; the whole waveform's
diluted most signatures in the one total gap (docs/validation.md, diagnose: whole waveform)."""

_ROUNDING_SD = 1.0 / np.sqrt(12.0)
"""SD of a uniform rounding error of one unit."""

FEATURE_SD_FLOOR: dict[str, float] = {
    "H": 0.05,  # m: echo timing precision of the CFD (|dR| < 0.10 m for 95 %, docs/method.md §(f))
    "Npeaks": _ROUNDING_SD,  # a count
    "Apeak": _ROUNDING_SD,  # DN: 8-bit rounding
    "FWHM": 0.1,  # ns: interpolated half-maximum crossings at 1-ns sampling
    "E": 1.0,  # DN ns: rounding of ~10 summed samples
    "n_echoes": _ROUNDING_SD,  # a count
    **WAVEFORM_SD_FLOOR,
}
"""Smallest meaningful SD of each feature (its measurement resolution), feature units."""

MIN_CELL_PULSES = 10
"""A cell enters the gap when it has at least this many real pulses ..."""

MIN_CELL_SAMPLES = 2
"""... from at least this many field samples (a cluster bootstrap needs several clusters)."""

_KEYS = ("dataset", "species", "sample_id")


# --------------------------------------------------------------------------------------
# per-sample sufficient statistics
# --------------------------------------------------------------------------------------


def sample_universe(*tables: pd.DataFrame) -> pd.Series:
    """The field samples of feature tables: ``sample_id -> species``, sorted by id.

    Parameters
    ----------
    *tables : DataFrame
        Feature tables with columns ``sample_id`` and ``species``.

    Returns
    -------
    Series
        Index sample_id (str), values species (str); the bootstrap's clusters and strata.
    """
    parts = []
    for t in tables:
        _require(t, ("sample_id", "species"), "feature table")
        parts.append(t[["sample_id", "species"]].astype(str))
    both = pd.concat(parts, ignore_index=True).drop_duplicates()
    dup = both["sample_id"].duplicated(keep=False)
    if dup.any():
        bad = sorted(both.loc[dup, "sample_id"].unique())[:5]
        raise WaveforestError(f"feature tables: sample_id(s) {bad} belong to more than one species")
    return both.set_index("sample_id")["species"].sort_index()



@dataclass
class GapData:
    """Real and simulated features reduced to per-sample sums, ready for bootstrapping.

    Attributes
    ----------
    cells : DataFrame
        C rows: dataset, species (the cell label: species and stratum; the cells present in the real table).
    features : tuple of str
        F feature names.
    floors : (F,) float64
        SD floors (:data:`FEATURE_SD_FLOOR`), feature units.
    universe : Series
        J samples, ``sample_id -> species``.
    n, s1, s2 : (2, C, F, J) float64
        Per source (0 real, 1 sim), cell, feature and sample: count of finite values, sum
        and sum of squares of the values minus ``center``.
    center : (C, F) float64
        Real mean per cell and feature (numerical centring only).
    valid : (C, F) bool
        Cells that enter the gap (enough real pulses and samples, >= 2 simulated values).
    real, sim : DataFrame
        The input rows (for the Wasserstein distance).
    floor_scale : float
        Factor on every noise floor (module docstring, Noise; 1 = the bootstrap's).
    """

    cells: pd.DataFrame
    features: tuple[str, ...]
    floors: np.ndarray
    universe: pd.Series
    n: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    center: np.ndarray
    valid: np.ndarray
    real: pd.DataFrame
    sim: pd.DataFrame
    floor_scale: float = 1.0

    @cached_property
    def label_members(self) -> np.ndarray:
        """(L, C) bool: the cells of each label (species and stratum), in order of appearance."""
        codes = pd.factorize(self.cells["species"])[0]
        return codes[None, :] == np.arange(codes.max() + 1)[:, None]

    @classmethod
    def build(
        cls,
        real: pd.DataFrame,
        sim: pd.DataFrame,
        universe: pd.Series | None = None,
        *,
        features: tuple[str, ...] = FEATURES,
        floors: dict[str, float] | None = None,
        min_pulses: int = MIN_CELL_PULSES,
        min_samples: int = MIN_CELL_SAMPLES,
        floor_scale: float = 1.0,
    ) -> GapData:
        """Reduce two feature tables to per-sample sums.

        Parameters
        ----------
        real, sim : DataFrame
            Feature tables (one row per pulse) with dataset, species, sample_id and the
            feature columns; NaN feature values are left out of that feature.
        universe : Series, optional
            The samples (``sample_id -> species``); default: those of the two tables. Pass
            one universe to compare several simulations against the same real table with
            the same bootstrap weights. Simulated samples outside it are an error.
        features : tuple of str
            Feature columns.
        floors : dict, optional
            SD floor per feature (default :data:`FEATURE_SD_FLOOR`; every feature needs one).
        min_pulses, min_samples : int
            Smallest real pulse and sample counts of a cell that enters the gap.
        floor_scale : float
            Factor on the noise floors (:attr:`floor_scale`).
        """
        if not (np.isfinite(floor_scale) and floor_scale > 0):
            raise WaveforestError(f"gap: floor_scale must be a positive number, got {floor_scale}")
        features = tuple(features)
        floors = {**FEATURE_SD_FLOOR, **(floors or {})}
        missing_floor = [f for f in features if f not in floors]
        if missing_floor:
            raise WaveforestError(f"gap: no SD floor for feature(s) {missing_floor}; pass floors=")
        for name, t in (("real", real), ("simulated", sim)):
            _require(t, _KEYS + features, f"{name} feature table")
        if universe is None:
            universe = sample_universe(real, sim)
        ds_names = pd.Index(sorted(real["dataset"].astype(str).unique()))
        sp_names = pd.Index(sorted(cell_label(real).unique()))
        code = _cell_codes(real, ds_names, sp_names)
        present = np.unique(code)
        lookup = np.full(len(ds_names) * len(sp_names), -1)
        lookup[present] = np.arange(len(present))
        cells = pd.DataFrame({"dataset": ds_names[present // len(sp_names)],
                              "species": sp_names[present % len(sp_names)]})
        n_c, n_f, n_j = len(cells), len(features), len(universe)
        shape = (2, n_c, n_f, n_j)
        n = np.zeros(shape)
        s1 = np.zeros(shape)
        s2 = np.zeros(shape)
        center = np.zeros((n_c, n_f))
        for src, table in enumerate((real, sim)):
            code = _cell_codes(table, ds_names, sp_names)
            c = np.where(code >= 0, lookup[np.maximum(code, 0)], -1)
            j = universe.index.get_indexer(table["sample_id"].astype(str))
            if src == 1 and np.any((j < 0) & (c >= 0)):
                bad = sorted(table.loc[(j < 0) & (c >= 0), "sample_id"].astype(str).unique())[:5]
                raise WaveforestError(f"simulated feature table: sample_id(s) {bad} are not in the real table")
            _add_sums(table, c, j, features, src, center, (n, s1, s2))
        n_real = n[0].sum(axis=-1)
        n_real_samples = (n[0] > 0).sum(axis=-1)
        valid = (n_real >= min_pulses) & (n_real_samples >= min_samples) & (n[1].sum(axis=-1) >= 2)
        return cls(
            cells=cells,
            features=features,
            floors=np.array([floors[f] for f in features], dtype=np.float64),
            universe=universe,
            n=n,
            s1=s1,
            s2=s2,
            center=center,
            valid=valid,
            real=real,
            sim=sim,
            floor_scale=float(floor_scale),
        )


def _add_sums(table: pd.DataFrame, c: np.ndarray, j: np.ndarray, features, src: int, center: np.ndarray,
              sums: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    """Fill ``n, s1, s2 [src]`` (and, for the real table, ``center``) from one table's rows.

    ``c`` and ``j`` are each row's cell and sample index (-1: not counted).
    """
    n, s1, s2 = sums
    n_c, n_j = n.shape[1], n.shape[3]
    keep = (c >= 0) & (j >= 0)
    flat = c[keep] * n_j + j[keep]
    for k, f in enumerate(features):
        x = table[f].to_numpy(dtype=np.float64)[keep]
        ok = np.isfinite(x)
        if src == 0:
            center[:, k] = _group_mean(c[keep][ok], x[ok], n_c)
        xc = x[ok] - center[c[keep][ok], k]
        n[src, :, k] = np.bincount(flat[ok], minlength=n_c * n_j).reshape(n_c, n_j)
        s1[src, :, k] = np.bincount(flat[ok], xc, minlength=n_c * n_j).reshape(n_c, n_j)
        s2[src, :, k] = np.bincount(flat[ok], xc * xc, minlength=n_c * n_j).reshape(n_c, n_j)


def _require(table: pd.DataFrame, columns, what: str) -> None:
    missing = [c for c in columns if c not in table.columns]
    if missing:
        raise WaveforestError(f"{what}: missing column(s) {', '.join(missing)}")


def cell_label(table: pd.DataFrame) -> pd.Series:
    """The species of each row, followed by its ``stratum`` where it has one (module docstring)."""
    species = table["species"].astype(str)
    if "stratum" not in table:
        return species
    stratum = table["stratum"].fillna("").astype(str)
    return species.where(stratum == "", species + " " + stratum)


def _cell_codes(table: pd.DataFrame, ds_names: pd.Index, sp_names: pd.Index) -> np.ndarray:
    """``dataset index * n_labels + cell label index`` per row; -1 where either is unknown."""
    d = ds_names.get_indexer(table["dataset"].astype(str))
    s = sp_names.get_indexer(cell_label(table))
    return np.where((d >= 0) & (s >= 0), d * len(sp_names) + s, -1)


def _group_mean(group: np.ndarray, x: np.ndarray, n_groups: int) -> np.ndarray:
    cnt = np.bincount(group, minlength=n_groups)
    tot = np.bincount(group, x, minlength=n_groups)
    return np.divide(tot, cnt, out=np.zeros(n_groups), where=cnt > 0)


# --------------------------------------------------------------------------------------
# statistics (point estimate and bootstrap replicates share one code path)
# --------------------------------------------------------------------------------------


def cell_statistics(data: GapData, weights: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Means, SDs, d and l of every cell and feature, for the data or bootstrap replicates.

    Parameters
    ----------
    data : GapData
    weights : (B, J) float64, optional
        Sample multiplicities (:func:`bootstrap_weights`); None = the data as observed.

    Returns
    -------
    dict of arrays, each (C, F) or (B, C, F)
        ``n_real, n_sim, mean_real, mean_sim, sd_real, sd_sim, pooled_sd, d, log_sd_ratio``;
        NaN where a source has fewer than 2 values.
    """
    if weights is None:
        n, s1, s2 = (a.sum(axis=-1) for a in (data.n, data.s1, data.s2))  # (2, C, F)
    else:
        weights = np.asarray(weights, dtype=np.float64)
        if weights.ndim != 2 or weights.shape[1] != len(data.universe):
            raise ValueError(f"weights must be (B, {len(data.universe)}), got {weights.shape}")
        n, s1, s2 = (np.einsum("bj,scfj->sbcf", weights, a) for a in (data.n, data.s1, data.s2))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = s1 / n
        var = np.maximum(s2 - s1 * mean, 0.0) / (n - 1)
        var = np.where(n >= 2, var, np.nan)
        mean = np.where(n >= 1, mean, np.nan)
        sd = np.sqrt(var)
        pooled = np.sqrt(((n[0] - 1) * var[0] + (n[1] - 1) * var[1]) / (n[0] + n[1] - 2))
        pooled = np.maximum(pooled, data.floors)
        d = (mean[1] - mean[0]) / pooled
        lsr = np.log(np.maximum(sd[1], data.floors) / np.maximum(sd[0], data.floors))
    return {
        "n_real": n[0],
        "n_sim": n[1],
        "mean_real": mean[0] + data.center,
        "mean_sim": mean[1] + data.center,
        "sd_real": sd[0],
        "sd_sim": sd[1],
        "pooled_sd": pooled,
        "d": d,
        "log_sd_ratio": lsr,
    }


def contributions(stats: dict[str, np.ndarray]) -> np.ndarray:
    """``d^2 + l^2`` per cell and feature (the moment-gap terms), same shape as ``d``."""
    return stats["d"] ** 2 + stats["log_sd_ratio"] ** 2


def pooled(data: GapData, x: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Mean of a per-cell statistic over the datasets of each label (module docstring, Total).

    Parameters
    ----------
    data : GapData
    x : (C, F) or (B, C, F) float64
        A statistic per cell and feature (e.g. ``d``), or its bootstrap replicates.
    mask : (C, F) bool
        Cells that enter; NaN values of ``x`` are left out of their label's mean.

    Returns
    -------
    (K,) or (B, K) float64
        One value per label x feature with at least one cell in ``mask`` (NaN where all of
        its cells are NaN).
    """
    member = data.label_members[:, :, None] & mask[None]  # (L, C, F)
    keep = member.any(axis=1)  # (L, F)
    member = member.astype(np.float64)  # einsum is faster on floats, and exact on 0 / 1
    ok = np.isfinite(x)
    num = np.einsum("lcf,...cf->...lf", member, np.where(ok, x, 0.0))
    den = np.einsum("lcf,...cf->...lf", member, ok.astype(np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        return (num / den)[..., keep]


def masked_gap(data: GapData, stats: dict[str, np.ndarray], mask: np.ndarray) -> float | np.ndarray:
    """G over the cells of ``mask``: mean of ``d_bar^2 + l_bar^2`` (float, or (B,) for
    bootstrap ``stats``; replicates in which a term is degenerate average the rest)."""
    terms = pooled(data, stats["d"], mask) ** 2 + pooled(data, stats["log_sd_ratio"], mask) ** 2
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN replicates of a tiny cell
        out = np.nanmean(terms, axis=-1)
    return float(out) if np.ndim(out) == 0 else out


def gap_interval(estimate: float, replicates: np.ndarray, alpha: float = DEFAULT_ALPHA) -> tuple[float, float]:
    """Interval of a gap (G, or a per-feature or per-cell part: all >= 0): the recentred
    bootstrap interval (:func:`waveforest.stats.bootstrap.recentred_interval`) with its bounds
    clipped at 0; NaN stays NaN."""
    lo, hi = recentred_interval(estimate, replicates, alpha)
    return float(np.maximum(lo, 0.0)), float(np.maximum(hi, 0.0))


def masked_floor(data: GapData, boot: dict[str, np.ndarray], mask: np.ndarray) -> float:
    """F over the cells of ``mask``: ``data.floor_scale`` x mean of ``Var*(d_bar) + Var*(l_bar)``
    from the bootstrap statistics ``boot`` ((B, C, F) arrays of :func:`cell_statistics`)."""
    v = robust_sd(pooled(data, boot["d"], mask)) ** 2 + robust_sd(pooled(data, boot["log_sd_ratio"], mask)) ** 2
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return float(np.nanmean(v)) * data.floor_scale


def masked_summary(data: GapData, point: dict, boot: dict, mask: np.ndarray,
                   alpha: float) -> tuple[float, float, float, float, np.ndarray]:
    """(G, its interval's lower and upper ends, F, G's bootstrap replicates) over the cells of
    ``mask``, from :func:`cell_statistics` of the data (``point``) and of bootstrap weights (``boot``)."""
    g, reps = masked_gap(data, point, mask), masked_gap(data, boot, mask)
    lo, hi = gap_interval(g, reps, alpha)
    return g, lo, hi, masked_floor(data, boot, mask), reps


def _mask(data: GapData, valid: np.ndarray | None, feature: str | None) -> np.ndarray:
    mask = data.valid if valid is None else np.asarray(valid, dtype=bool)
    if feature is not None:
        mask = mask & (np.asarray(data.features) == feature)[None, :]
    if not mask.any():
        raise WaveforestError("gap: no cell has enough real and simulated pulses to compare")
    return mask


def total_gap(
    data: GapData,
    weights: np.ndarray | None = None,
    valid: np.ndarray | None = None,
    feature: str | None = None,
) -> float | np.ndarray:
    """The moment gap G: mean of ``d_bar^2 + l_bar^2`` over labels (and features).

    Parameters
    ----------
    data : GapData
    weights : (B, J) float64, optional
        Bootstrap multiplicities; None = point estimate.
    valid : (C, F) bool, optional
        Cells that enter (default ``data.valid``); pass a common mask when comparing
        simulations so that every gap averages the same cells.
    feature : str, optional
        Restrict to one feature (the per-feature gap).

    Returns
    -------
    float, or (B,) float64 with weights
        Squared pooled SDs.
    """
    return masked_gap(data, cell_statistics(data, weights), _mask(data, valid, feature))


def total_noise_floor(data: GapData, weights: np.ndarray, valid: np.ndarray | None = None) -> float:
    """The noise floor F of the total gap over ``valid`` (default ``data.valid``)."""
    return masked_floor(data, cell_statistics(data, weights), _mask(data, valid, None))


# --------------------------------------------------------------------------------------
# reports
# --------------------------------------------------------------------------------------


def _total_row(column: str, kind: type, doc: str) -> property:
    """A read-only property: ``kind`` of the ``total`` row's ``column`` of a report's ``summary``."""
    return property(lambda self: kind(self.summary.loc["total", column]), doc=doc)


@dataclass
class GapReport:
    """The gap of one simulation against the real data, with intervals.

    Attributes
    ----------
    cells : DataFrame
        One row per dataset x species x feature: n_real, n_sim, n_samples, mean_real,
        mean_sim, sd_real, sd_sim, pooled_sd, d (+ d_ci_low/high), log_sd_ratio
        (+ lsr_ci_low/high), w1 (+ w1_ci_low/high), contribution (d^2 + l^2), noise
        (Var d + Var l), valid.
    summary : DataFrame
        One row per feature and a last row ``total``: gap, ci_low, ci_high (>= 0), noise_floor,
        excess, excess_ci_low, excess_ci_high (ci_low/high - noise_floor), significant
        (excess_ci_low > 0), w1 (mean over cells), n_cells.
    replicates : (B,) float64
        Bootstrap replicates of the total gap.
    """

    cells: pd.DataFrame
    summary: pd.DataFrame
    replicates: np.ndarray

    total = _total_row("gap", float, "Total moment gap G, squared pooled SDs (float).")
    noise_floor = _total_row("noise_floor", float, "Total noise floor F (float).")
    excess = _total_row("excess", float, "G - F (float).")
    significant = _total_row("significant", bool, "Whether the total excess gap's interval lies above 0 (bool).")


def gap_report(
    real: pd.DataFrame,
    sim: pd.DataFrame,
    *,
    n_boot: int = 200,
    seed=0,
    alpha: float = DEFAULT_ALPHA,
    features: tuple[str, ...] = FEATURES,
    floors: dict[str, float] | None = None,
    min_pulses: int = MIN_CELL_PULSES,
    min_samples: int = MIN_CELL_SAMPLES,
    wasserstein: bool = True,
    universe: pd.Series | None = None,
    weights: np.ndarray | None = None,
    floor_scale: float = 1.0,
) -> GapReport:
    """The gap between real and simulated features, per cell, per feature and in total.

    Parameters
    ----------
    real, sim : DataFrame
        Feature tables (dataset, species, sample_id and the feature columns).
    n_boot : int
        Cluster-bootstrap replicates (field samples resampled within species).
    seed : int
        Seed of the bootstrap.
    alpha : float
        Two-sided level of the intervals.
    features, floors, min_pulses, min_samples, floor_scale
        See :meth:`GapData.build`.
    wasserstein : bool
        Also compute w (and its interval) per cell; the slowest part.
    universe, weights : optional
        Shared samples and bootstrap weights (to pair this report with another one).

    Returns
    -------
    GapReport
    """
    data = GapData.build(real, sim, universe, features=features, floors=floors,
                         min_pulses=min_pulses, min_samples=min_samples, floor_scale=floor_scale)
    if weights is None:
        weights = bootstrap_weights(data.universe, n_boot, seed)
    if not data.valid.any():
        raise WaveforestError("gap: no cell has enough real and simulated pulses to compare")
    point = cell_statistics(data)
    boot = cell_statistics(data, weights)
    terms = contributions(point)
    noise = np.where(data.valid, robust_sd(boot["d"]) ** 2 + robust_sd(boot["log_sd_ratio"]) ** 2, np.nan)
    noise = noise * data.floor_scale
    q = [alpha / 2, 1 - alpha / 2]
    df = np.maximum((data.n[0] > 0).sum(axis=-1) - 1, 1)
    d_ci = wald_interval(point["d"], boot["d"], df, alpha)
    l_ci = wald_interval(point["log_sd_ratio"], boot["log_sd_ratio"], df, alpha)
    w1 = np.full(data.valid.shape, np.nan)
    w1_ci = np.full((2,) + data.valid.shape, np.nan)
    if wasserstein:
        w1, w1_ci = wasserstein_cells(data, point["pooled_sd"], weights, q)
    cells = _cells_table(data, point, terms, noise, d_ci, l_ci, w1, w1_ci)
    summary, total_reps = _summary_table(data, point, boot, w1 if wasserstein else None, alpha)
    return GapReport(cells=cells, summary=summary, replicates=total_reps)


def _cells_table(data: GapData, point: dict, terms, noise, d_ci, l_ci, w1, w1_ci) -> pd.DataFrame:
    """:attr:`GapReport.cells`: one row per cell and feature."""
    rows = []
    for c, (ds, sp) in enumerate(data.cells.itertuples(index=False)):
        for k, f in enumerate(data.features):
            rows.append({
                "dataset": ds, "species": sp, "feature": f,
                "n_real": int(point["n_real"][c, k]), "n_sim": int(point["n_sim"][c, k]),
                "n_samples": int((data.n[0, c, k] > 0).sum()),
                "mean_real": point["mean_real"][c, k], "mean_sim": point["mean_sim"][c, k],
                "sd_real": point["sd_real"][c, k], "sd_sim": point["sd_sim"][c, k],
                "pooled_sd": point["pooled_sd"][c, k],
                "d": point["d"][c, k], "d_ci_low": d_ci[0, c, k], "d_ci_high": d_ci[1, c, k],
                "log_sd_ratio": point["log_sd_ratio"][c, k],
                "lsr_ci_low": l_ci[0, c, k], "lsr_ci_high": l_ci[1, c, k],
                "w1": w1[c, k], "w1_ci_low": w1_ci[0, c, k], "w1_ci_high": w1_ci[1, c, k],
                "contribution": terms[c, k], "noise": noise[c, k], "valid": bool(data.valid[c, k]),
            })
    return pd.DataFrame(rows)


def _summary_table(data: GapData, point: dict, boot: dict, w1, alpha: float) -> tuple[pd.DataFrame, np.ndarray]:
    """:attr:`GapReport.summary` (per feature and ``total``) and the total gap's replicates.

    ``w1`` is None when the Wasserstein distances were not computed.
    """
    summary_rows = {}
    total_reps = None
    for f in list(data.features) + ["total"]:
        mask = data.valid & ((np.asarray(data.features) == f)[None, :] if f != "total" else True)
        if not mask.any():
            summary_rows[f] = {"gap": np.nan, "ci_low": np.nan, "ci_high": np.nan, "noise_floor": np.nan,
                               "excess": np.nan, "excess_ci_low": np.nan, "excess_ci_high": np.nan,
                               "significant": False, "w1": np.nan, "n_cells": 0}
            continue
        g, lo, hi, fl, reps = masked_summary(data, point, boot, mask, alpha)
        summary_rows[f] = {
            "gap": g, "ci_low": lo, "ci_high": hi, "noise_floor": fl,
            "excess": g - fl, "excess_ci_low": lo - fl, "excess_ci_high": hi - fl,
            "significant": bool(lo - fl > 0), "w1": float(np.nanmean(w1[mask])) if w1 is not None else np.nan,
            "n_cells": int(mask.sum()),
        }
        if f == "total":
            total_reps = reps
    summary = pd.DataFrame.from_dict(summary_rows, orient="index")
    summary.index.name = "feature"
    return summary, total_reps


def wasserstein_cells(data: GapData, pooled: np.ndarray, weights: np.ndarray, q) -> tuple[np.ndarray, np.ndarray]:
    """W1 / pooled SD per cell and feature, and its bootstrap percentile interval.

    The bootstrap reuses the sample multiplicities as pulse weights (scipy's weighted W1),
    so no resampled arrays are built.
    """
    from scipy.stats import wasserstein_distance

    n_c, n_f = data.valid.shape
    w1 = np.full((n_c, n_f), np.nan)
    ci = np.full((2, n_c, n_f), np.nan)
    uni = data.universe.index
    by_cell = []
    for table in (data.real, data.sim):
        key = table["dataset"].astype(str) + "\x00" + cell_label(table)
        by_cell.append((key.to_numpy(), uni.get_indexer(table["sample_id"].astype(str))))
    for c, (ds, sp) in enumerate(data.cells.itertuples(index=False)):
        sel = [k == f"{ds}\x00{sp}" for k, _ in by_cell]
        for k, f in enumerate(data.features):
            if not data.valid[c, k]:
                continue
            xs, js = [], []
            for src, table in enumerate((data.real, data.sim)):
                x = table[f].to_numpy(dtype=np.float64)[sel[src]]
                j = by_cell[src][1][sel[src]]
                ok = np.isfinite(x) & (j >= 0)
                xs.append(x[ok])
                js.append(j[ok])
            w1[c, k] = wasserstein_distance(xs[1], xs[0]) / pooled[c, k]
            reps = np.full(len(weights), np.nan)
            for b in range(len(weights)):
                wr, ws = weights[b, js[0]], weights[b, js[1]]
                if wr.sum() > 0 and ws.sum() > 0:
                    reps[b] = wasserstein_distance(xs[1], xs[0], ws, wr) / pooled[c, k]
            if np.isfinite(reps).any():
                ci[:, c, k] = np.nanquantile(reps, q)
    return w1, ci
