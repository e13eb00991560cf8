"""The search: which missing effect explains the gap, at what value, and how sure are we.

Procedure (one *round*; :func:`search` runs up to ``rounds`` of them)
--------------------------------------------------------------------
1. **Split.** The field samples of every species are split at random into halves A and B
   (all pulses of a sample, in every dataset, go to the same half: they are correlated).
   The split is drawn once and kept for every round. Each half has its own simulation seed.
2. **Fit** each candidate effect not yet in the model on one half: simulate that half's
   fit pulses (all, or a random subset: ``fit_keys``) with the current model plus the
   candidate at each value of a grid over its search
   coordinate (:func:`.catalogue.grid`, always containing "off" = the current model), then
   refine with a few Brent-like steps (:func:`refinement_step`: a new simulation at the
   vertex of the parabola through the best point and its neighbours, or a golden-section
   step). Every value uses the **same seed** (common random numbers): the gap curve G(u)
   then varies with the effect, not with simulation noise, and the current model's own
   simulation serves as the "off" point. The fitted value minimises G. Its interval: the
   same cluster-bootstrap resamples applied to every simulated value give a gap curve per
   replicate, whose parabolic minimum is a replicate of the fitted value.
3. **Test** the fitted candidate on all pulses of the *other* half (simulated with that
   half's seed, as the current model is): the reduction R = G_current - G_candidate, with a paired cluster
   bootstrap. With ``crossfit`` (default) the roles are then swapped (fit on B, test on
   A) and both fits and both reductions are averaged: every sample is used for testing,
   which halves the variance of R at twice the simulations. The named value is the mean
   of the two fits; its interval is the percentile interval of the replicate-wise means.
   A candidate is *significant* when ``R -+ t * SE*`` (:func:`.gap.wald_interval`) lies
   above 0 AND R is at least ``min_relative_reduction`` of the current model's excess gap
   on the tested samples (a real, not a cosmetic, improvement) AND the fitted value's
   interval excludes the effect's off value (the fits, too, must ask for the effect: on 160
   birch samples with a hidden understory the best candidate was a LAD shift of -1.6 deg
   [-2.5, +0.06], significant in R only because it also nudged a small Npeaks residual of
   the base model). No multiplicity correction
   over the candidates: a candidate whose signature is unrelated to the gap has R <= 0 in
   expectation (it adds its own shift), and one partly aligned with a real gap does reduce
   it; the relative threshold, not the interval, keeps such a partial explanation from
   being named. The power is limited by the squared measure: a candidate that removes a
   shift delta is told apart from the current model with z = delta / (2 SE(d)), half the z
   of the shift itself (which of two models is closer to noisy data is decided at their
   midpoint) — hence cross-fitting.
4. **Name** the candidate with the largest R if it is significant, add it at its fitted
   value. A candidate whose fit lies at the far edge of its range (:func:`at_bound`) is
   ranked but not named: the data ask it for a value beyond what is plausible, the mark of
   a look-alike standing in for another effect (seen with a hidden ``hotspot`` 1.3 and
   ``clumping`` 0.15, where ``leaf_albedo`` pinned at its bound 1.2 edged out ``hotspot``
   by 0.009 of 0.43 in gap reduction); the best candidate fitted inside its range takes
   its place. From the second effect on, re-fit all named effects, each with the others
   fixed, until they stop moving (coordinate descent, :data:`REFIT_PASSES`). Otherwise a
   lower-ranked candidate is never named in its place, even when its own interval clears zero: the data
   then say that another effect explains the gap better, only less certainly, and naming
   the narrower interval would name the wrong effect (seen with a hidden ``lad_shift``,
   whose look-alike ``leaf_albedo`` ranked second); the reason then names the significant
   candidates whose reduction is not told apart from the best's (:func:`look_alikes`).
   Stop when the best candidate is not significant, when ``rounds`` effects are named, or
   when the model's gap on all samples is no longer significant above the noise floor.

Verdict: ``none`` when the base model's gap is not significant above its noise floor (no
effect is named, whatever the candidates do); ``named`` when at least one effect was named;
``unexplained`` when the gap is significant but no candidate passes. Forward selection is
greedy: when two hidden effects have overlapping signatures, the first round may name a
third effect that mimics their sum (the ranked evidence table shows how close the
runners-up were: ``vs_best_ci_low/high``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose import gap as _gap
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError

Simulator = Callable[[pd.DataFrame, dict, int], pd.DataFrame]
"""``simulate(pulses, effects, seed) -> feature table``: one row per simulated pulse with
dataset, sample_id, species and the feature columns. ``pulses`` is a subset of the search's
pulse table (rows kept whole, plus a ``replicate`` column); the same seed must give the same
random numbers whatever the effect values (common random numbers)."""

VERDICTS = ("none", "named", "unexplained")

HALVES = ("A", "B")
"""Names of the two halves of the field samples."""

REFIT_PASSES = 3
"""Most coordinate-descent passes over the named effects after a new one is named."""

_REFIT_TOL_U = 0.01
"""A pass that moves no named effect by more than this (search coordinate) ends the re-fit."""

_VERTEX_TOL_U = 1e-3
"""A refinement step closer than this (search coordinate) to an evaluated value is not taken."""

_GOLDEN = (3.0 - math.sqrt(5.0)) / 2.0
"""Golden-section fraction (0.382) of Brent's method."""

_MAX_BRACKET_ASYMMETRY = 3.0
"""A bracket whose long side exceeds this many times its short side gets a golden step
into the long side: parabolic steps there creep along the short side (slow convergence)."""


@dataclass(frozen=True)
class SearchSettings:
    """Settings of the search (config section ``diagnose``).

    Attributes
    ----------
    rounds : int
        Most effects named.
    n_boot : int
        Cluster-bootstrap replicates.
    values : int
        Grid values per candidate (including "off").
    refine : int
        Refinement steps per candidate fit (one simulation each).
    replicates : int
        Simulated pulses per real pulse and value.
    alpha : float
        Two-sided level of the intervals.
    min_relative_reduction : float
        Smallest share of the current excess gap a named effect must remove.
    candidates : tuple of str
        Effects tried (default: the whole catalogue).
    refit : bool
        Re-fit earlier effects after naming a new one.
    crossfit : bool
        Fit on each half and test on the other (both directions), or only fit A / test B.
    features, floors, min_pulses, min_samples
        Gap settings (:meth:`.gap.GapData.build`).
    """

    rounds: int = 3
    n_boot: int = 200
    values: int = 5
    refine: int = 3
    replicates: int = 2
    alpha: float = _gap.DEFAULT_ALPHA
    min_relative_reduction: float = 0.2
    candidates: tuple[str, ...] = tuple(CATALOGUE)
    refit: bool = True
    crossfit: bool = True
    features: tuple[str, ...] = _gap.FEATURES
    floors: dict | None = None
    min_pulses: int = _gap.MIN_CELL_PULSES
    min_samples: int = _gap.MIN_CELL_SAMPLES

    def __post_init__(self) -> None:
        for name in self.candidates:
            cat.effect(name)
        if self.rounds < 1 or self.values < 3 or self.refine < 0 or self.replicates < 1 or self.n_boot < 10:
            raise WaveforestError(
                "diagnose: need rounds >= 1, values >= 3, refine >= 0, pulses_per_value >= 1, bootstrap >= 10"
            )
        if not 0 < self.alpha < 1:
            raise WaveforestError(f"diagnose.alpha must be in (0, 1), got {self.alpha}")

    @classmethod
    def from_config(cls, cfg: dict) -> SearchSettings:
        """Settings from a loaded study config (section ``diagnose``)."""
        d = cfg["diagnose"]
        return cls(
            rounds=int(d["rounds"]),
            n_boot=int(d["bootstrap"]),
            values=int(d["values"]),
            refine=int(d["refine"]),
            replicates=int(d["pulses_per_value"]),
            alpha=float(d["alpha"]),
            min_relative_reduction=float(d["min_relative_reduction"]),
            candidates=tuple(d["candidates"] or CATALOGUE),
            refit=bool(d["refit"]),
            crossfit=bool(d["crossfit"]),
            features=tuple(d["features"]),
            min_pulses=int(d["min_cell_pulses"]),
            min_samples=int(d["min_cell_samples"]),
        )

    @property
    def gap_kw(self) -> dict:
        """Keyword arguments of :meth:`.gap.GapData.build`."""
        return {"features": self.features, "floors": self.floors,
                "min_pulses": self.min_pulses, "min_samples": self.min_samples}

    @property
    def folds(self) -> tuple[tuple[str, str], ...]:
        """(fit half, test half) pairs."""
        return (("A", "B"), ("B", "A")) if self.crossfit else (("A", "B"),)


@dataclass
class Fit:
    """A candidate's 1-D fit on one half.

    Attributes
    ----------
    name, half : str
    u, gap : (k,) float64
        Evaluated search coordinates (sorted) and the half's gap at each.
    u_hat : float
        Fitted search coordinate.
    u_boot : (B,) float64
        Bootstrap replicates of ``u_hat`` (NaN where a replicate curve is degenerate).
    """

    name: str
    half: str
    u: np.ndarray
    gap: np.ndarray
    u_hat: float
    u_boot: np.ndarray = field(repr=False)


@dataclass
class Estimate:
    """A fitted value (mean over folds) and its percentile bootstrap interval."""

    name: str
    u_hat: float
    value: float
    ci_low: float
    ci_high: float
    u_low: float
    u_high: float

    @property
    def excludes_off(self) -> bool:
        """Whether the interval (search coordinate) leaves out the effect's off value."""
        return not self.u_low <= cat.off_u(self.name) <= self.u_high

    @classmethod
    def combine(cls, fits: list[Fit], alpha: float) -> Estimate:
        """Mean of the folds' fits; interval from the replicate-wise means."""
        name = fits[0].name
        u_hat = float(np.mean([f.u_hat for f in fits]))
        u_b = np.mean([f.u_boot for f in fits], axis=0)
        u_b = u_b[np.isfinite(u_b)]
        lo, hi = np.quantile(u_b, [alpha / 2, 1 - alpha / 2]) if u_b.size else (u_hat, u_hat)
        v_lo, v_hi = cat.value_interval(name, lo, hi)
        return cls(name=name, u_hat=u_hat, value=cat.from_u(name, u_hat), ci_low=v_lo, ci_high=v_hi,
                   u_low=float(lo), u_high=float(hi))


AT_BOUND_U = 0.02
"""A fit within this distance (search coordinate, 0 ... 1 over the bounds) of the bound
that is not the effect's off value is *at the bound*."""


def at_bound(name: str, u_hat: float) -> bool:
    """Whether a fit lies at the far edge of the effect's range (:data:`AT_BOUND_U`): the
    data then ask for a value beyond what the catalogue deems plausible."""
    u0 = cat.off_u(name)
    return bool((u_hat <= AT_BOUND_U and u0 > AT_BOUND_U) or (u_hat >= 1 - AT_BOUND_U and u0 < 1 - AT_BOUND_U))


@dataclass
class Candidate:
    """A candidate's fit and test in one round (one row of ``candidates.csv``)."""

    round: int
    estimate: Estimate
    gap_base: float
    gap_new: float
    excess_base: float
    reduction: float
    reduction_ci_low: float
    reduction_ci_high: float
    relative: float
    significant: bool
    replicates: np.ndarray = field(repr=False)

    def row(self) -> dict:
        """The ``candidates.csv`` row."""
        e = self.estimate
        return {
            "round": self.round, "name": e.name, "value": e.value, "ci_low": e.ci_low, "ci_high": e.ci_high,
            "gap_base": self.gap_base, "gap_new": self.gap_new,
            "gap_reduction": self.reduction, "reduction_ci_low": self.reduction_ci_low,
            "reduction_ci_high": self.reduction_ci_high, "relative_reduction": self.relative,
            "significant": self.significant, "at_bound": at_bound(e.name, e.u_hat),
        }


@dataclass
class NamedEffect:
    """An effect added to the model (one entry of ``model.yaml``)."""

    name: str
    value: float
    ci_low: float
    ci_high: float
    gap_reduction: float
    reduction_ci_low: float
    reduction_ci_high: float
    relative_reduction: float
    round: int
    look_alikes: list[str] = field(default_factory=list)
    """Candidates of its round that reduced the gap significantly too, by an amount not told
    apart from its own (:func:`look_alikes`): on these data, as good an explanation."""


@dataclass
class SearchResult:
    """Everything the search found.

    Attributes
    ----------
    verdict : str
        ``none``, ``named`` or ``unexplained``.
    named : list of NamedEffect
        In the order named (values after the last re-fit).
    candidates : DataFrame
        Every candidate of every round (:meth:`Candidate.row`), ranked by reduction within a
        round (``rank``), with the paired interval of its difference to the round's best
        (``vs_best_ci_low/high`` of R_best - R, best = the best candidate fitted inside its
        range) and ``at_bound`` (:func:`at_bound`).
    curves : DataFrame
        round, name, half, u, value, gap: the fitted gap curves.
    baseline, residual : GapReport
        Gap on all samples of the base model and of the final model (search simulations).
    reason : str
        One sentence on why the search stopped.
    n_simulations : int
        Simulator calls (each over one half, all replicates).
    halves : dict
        ``{"A": [sample ids], "B": [...]}``.
    simulations, test_simulations : _Simulations
        The caches of every simulation run on the fit pulses and on the tested pulses (the
        same object when all pulses are fitted); ``.all(effects)`` gives all samples under
        a model, simulating only what is not cached.
    """

    verdict: str
    named: list[NamedEffect]
    candidates: pd.DataFrame
    curves: pd.DataFrame
    baseline: _gap.GapReport
    residual: _gap.GapReport
    reason: str
    n_simulations: int
    halves: dict
    simulations: _Simulations = field(default=None, repr=False)
    test_simulations: _Simulations = field(default=None, repr=False)

    @property
    def effects(self) -> dict[str, float]:
        """The named effects as a simulation ``effects`` dict."""
        return {e.name: e.value for e in self.named}


# --------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------


def split_samples(keys: pd.DataFrame, seed) -> tuple[list[str], list[str]]:
    """Random halves of the field samples, stratified by species and datasets.

    A stratum is a species and the set of datasets its samples appear in (the samples of a
    year are seen by that year's datasets), so every dataset x species cell gets about half
    of its samples in each half. Odd strata give their extra sample alternately to A and B.

    Parameters
    ----------
    keys : DataFrame
        Pulses with dataset, sample_id and species.

    Returns
    -------
    a, b : list of str
        Sample ids, sorted.
    """
    uni = _gap.sample_universe(keys)
    seen = keys.assign(sample_id=keys["sample_id"].astype(str), dataset=keys["dataset"].astype(str))
    seen = seen.groupby("sample_id")["dataset"].agg(lambda d: ",".join(sorted(set(d))))
    stratum = uni.astype(str) + "|" + seen.reindex(uni.index).fillna("").astype(str)
    rng = np.random.default_rng(seed)
    a, b = [], []
    extra_to_a = True
    for st in sorted(stratum.unique()):
        ids = np.array(sorted(stratum.index[stratum.to_numpy() == st]))
        rng.shuffle(ids)
        k = len(ids) // 2
        if len(ids) % 2:
            k += int(extra_to_a)
            extra_to_a = not extra_to_a
        a += ids[:k].tolist()
        b += ids[k:].tolist()
    return sorted(a), sorted(b)


def parabolic_vertex(u: np.ndarray, g: np.ndarray) -> float | np.ndarray:
    """Minimum of the parabola through the best evaluated point and its two neighbours.

    Parameters
    ----------
    u : (k,) float64, sorted ascending, k >= 3
    g : (k,) or (B, k) float64
        Gap at each u (several curves: one vertex per row).

    Returns
    -------
    float or (B,) float64
        Vertex clipped to the best point's bracket [u[i-1], u[i+1]]; the best point itself
        where the parabola is not convex; NaN for a curve with a non-finite value.
    """
    single = np.ndim(g) == 1
    g = np.atleast_2d(np.asarray(g, dtype=np.float64))
    u = np.asarray(u, dtype=np.float64)
    k = len(u)
    finite = np.all(np.isfinite(g), axis=1)
    gg = np.where(finite[:, None], g, 0.0)
    i = np.argmin(gg, axis=1)
    j = np.clip(i, 1, k - 2)
    x0, x1, x2 = u[j - 1], u[j], u[j + 1]
    rows = np.arange(len(g))
    y0, y1, y2 = gg[rows, j - 1], gg[rows, j], gg[rows, j + 1]
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2**2 * (y0 - y1) + x1**2 * (y2 - y0) + x0**2 * (y1 - y2)) / den
    lo, hi = u[np.maximum(i - 1, 0)], u[np.minimum(i + 1, k - 1)]
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.clip(-b / (2 * a), lo, hi)
    out = np.where(a > 0, vertex, u[i])
    out = np.where(finite, out, np.nan)
    return float(out[0]) if single else out


def refinement_step(u: np.ndarray, g: np.ndarray) -> float | None:
    """Next value to evaluate: a Brent-like step inside the bracket of the best point.

    The vertex of the parabola through the best point and its neighbours, unless the
    bracket is lopsided (:data:`_MAX_BRACKET_ASYMMETRY`), the parabola is not convex or its
    vertex is within :data:`_VERTEX_TOL_U` of an evaluated value; then the golden-section
    point of the longer side of the bracket (which always shrinks the bracket, so strongly
    asymmetric curves, e.g. the tanh saturation, still converge). None when the bracket is
    narrower than the tolerance.

    Parameters
    ----------
    u : (k,) float64, sorted ascending
    g : (k,) float64
    """
    i = int(np.argmin(g))
    lo, hi = u[max(i - 1, 0)], u[min(i + 1, len(u) - 1)]
    if hi - lo < 2 * _VERTEX_TOL_U:
        return None
    left, right = u[i] - lo, hi - u[i]
    golden = u[i] + _GOLDEN * right if right >= left else u[i] - _GOLDEN * left
    lopsided = min(left, right) > 0 and max(left, right) > _MAX_BRACKET_ASYMMETRY * min(left, right)
    if not lopsided:
        j = min(max(i, 1), len(u) - 2)
        x0, x1, x2 = u[j - 1], u[j], u[j + 1]
        y0, y1, y2 = g[j - 1], g[j], g[j + 1]
        convex = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / ((x0 - x1) * (x0 - x2) * (x1 - x2)) > 0
        v = parabolic_vertex(u, g)
        if convex and np.min(np.abs(u - v)) >= _VERTEX_TOL_U:
            return float(v)
    return None if np.min(np.abs(u - golden)) < _VERTEX_TOL_U else float(golden)


class _Simulations:
    """Cache of simulator calls keyed by (half, effects); one seed per half."""

    def __init__(self, simulate: Simulator, halves: dict[str, pd.DataFrame], seeds: dict[str, int],
                 replicates: int, progress: Callable[[str], None] | None):
        self.simulate = simulate
        self.halves = halves
        self.seeds = seeds
        self.replicates = replicates
        self.progress = progress
        self.cache: dict = {}
        self.calls = 0

    def get(self, half: str, effects: dict[str, float]) -> pd.DataFrame:
        """Simulated features of ``half`` under ``effects`` (all replicates, cached)."""
        key = (half, tuple(sorted((k, round(float(v), 12)) for k, v in effects.items())))
        if key not in self.cache:
            keys = self.halves[half]
            reps = []
            for r in range(self.replicates):
                seed = int(np.random.SeedSequence([self.seeds[half], r]).generate_state(1)[0])
                out = self.simulate(keys.assign(replicate=r), dict(effects), seed)
                if not isinstance(out, pd.DataFrame):
                    raise WaveforestError("diagnose: the simulator must return a pandas DataFrame")
                reps.append(out)
            self.cache[key] = pd.concat(reps, ignore_index=True)
            self.calls += 1
            if self.progress is not None:
                self.progress(f"{half} {dict(effects)}")
        return self.cache[key]

    def all(self, effects: dict[str, float]) -> pd.DataFrame:
        """Simulated features of all samples (both halves) under ``effects``."""
        return pd.concat([self.get(h, effects) for h in HALVES if len(self.halves[h])], ignore_index=True)


@dataclass
class _Half:
    real: pd.DataFrame
    universe: pd.Series
    weights: np.ndarray


class _Context:
    """What every step of one search shares: halves, simulations, settings.

    ``halves``/``sims`` hold the fit pulses of each half, ``test_halves``/``test_sims`` the
    tested pulses (the same objects when every pulse is fitted).
    """

    def __init__(self, halves: dict[str, _Half], sims: _Simulations, settings: SearchSettings,
                 test_halves: dict[str, _Half] | None = None, test_sims: _Simulations | None = None):
        self.halves = halves
        self.sims = sims
        self.settings = settings
        self.test_halves = halves if test_halves is None else test_halves
        self.test_sims = sims if test_sims is None else test_sims

    def data(self, half: str, effects: dict) -> _gap.GapData:
        """Gap data of the fit pulses of ``half`` under ``effects``."""
        h = self.halves[half]
        return _gap.GapData.build(h.real, self.sims.get(half, effects), h.universe, **self.settings.gap_kw)

    def test_data(self, half: str, effects: dict) -> _gap.GapData:
        """Gap data of the tested pulses of ``half`` under ``effects``."""
        h = self.test_halves[half]
        return _gap.GapData.build(h.real, self.test_sims.get(half, effects), h.universe, **self.settings.gap_kw)


# --------------------------------------------------------------------------------------
# fit and test of one candidate
# --------------------------------------------------------------------------------------


def fit_candidate(name: str, current: dict[str, float], ctx: _Context, half: str) -> Fit:
    """1-D fit of one effect on one half (grid + Brent-like refinement, common seed).

    Parameters
    ----------
    name : str
        Effect to fit.
    current : dict
        The other effects of the model (fixed); ``name`` in it is ignored.
    ctx : _Context
        Halves, simulation cache and settings of the search.
    half : str
        ``"A"`` or ``"B"``.
    """
    settings = ctx.settings
    others = {k: v for k, v in current.items() if k != name}
    u0 = cat.off_u(name)

    def data_at(u: float) -> _gap.GapData:
        eff = others if abs(u - u0) < 1e-12 else cat.with_effect(others, name, cat.from_u(name, u))
        return ctx.data(half, eff)

    us = list(cat.grid(name, settings.values))
    datas = [data_at(u) for u in us]
    for _ in range(settings.refine):
        valid = np.logical_and.reduce([d.valid for d in datas])
        order = np.argsort(us)
        g = np.array([_gap.total_gap(datas[i], valid=valid) for i in order])
        v = refinement_step(np.asarray(us)[order], g)
        if v is None:
            break
        us.append(v)
        datas.append(data_at(v))
    order = np.argsort(us)
    u_arr = np.asarray(us)[order]
    datas = [datas[i] for i in order]
    valid = np.logical_and.reduce([d.valid for d in datas])
    g = np.array([_gap.total_gap(d, valid=valid) for d in datas])
    w = ctx.halves[half].weights
    reps = np.stack([_gap.total_gap(d, w, valid) for d in datas], axis=1)  # (B, k)
    return Fit(name=name, half=half, u=u_arr, gap=g, u_hat=float(parabolic_vertex(u_arr, g)),
               u_boot=parabolic_vertex(u_arr, reps))


def _fit(name: str, current: dict, ctx: _Context) -> tuple[Estimate, list[Fit]]:
    fits = [fit_candidate(name, current, ctx, f) for f, _ in ctx.settings.folds]
    return Estimate.combine(fits, ctx.settings.alpha), fits


def _test(current: dict, models_by_fold: list[dict], ctx: _Context):
    """Reduction of the gap on the test halves: (gap_base, gap_new, excess, R, R replicates).

    ``models_by_fold[k]`` is the model tested on fold k's test half (with fold k's fit).
    """
    gb, gn, ex, rep = [], [], [], []
    for (_, t), eff in zip(ctx.settings.folds, models_by_fold):
        base, cand = ctx.test_data(t, current), ctx.test_data(t, eff)
        valid = base.valid & cand.valid
        w = ctx.test_halves[t].weights
        gb.append(_gap.total_gap(base, valid=valid))
        gn.append(_gap.total_gap(cand, valid=valid))
        ex.append(gb[-1] - float(np.nanmean(_gap.noise_floor(base, w, valid)[valid])))
        rep.append(_gap.total_gap(base, w, valid) - _gap.total_gap(cand, w, valid))
    # folds test disjoint halves with independent resamples: replicate-wise mean is a replicate of the mean
    return float(np.mean(gb)), float(np.mean(gn)), float(np.mean(ex)), float(np.mean(gb) - np.mean(gn)), \
        np.mean(rep, axis=0)


def _refit(named: list[NamedEffect], current: dict, ctx: _Context) -> dict:
    """Coordinate descent: re-fit each named effect with the others fixed, until stable.

    Signatures overlap (e.g. hotspot and trigger_loss both change Apeak), so the value an
    effect got before a second one was added is biased; a few passes move the values to
    the joint minimum of the gap. ``named`` is updated in place (value and interval);
    returns the new model.
    """
    for _ in range(REFIT_PASSES):
        moved = 0.0
        for k, e in enumerate(named):
            est, _ = _fit(e.name, current, ctx)
            moved = max(moved, abs(est.u_hat - cat.to_u(e.name, current.get(e.name, cat.effect(e.name).off))))
            current = cat.with_effect(current, e.name, est.value)
            named[k] = replace(e, value=est.value, ci_low=est.ci_low, ci_high=est.ci_high)
        if moved < _REFIT_TOL_U:
            break
    return current


def look_alikes(rows: list[dict], best: str) -> list[str]:
    """Candidates of one round (``candidates.csv`` rows) that reduce the gap significantly and
    that the data cannot tell apart from ``best``: their ``vs_best`` interval covers 0."""
    return [r["name"] for r in rows if r["name"] != best and r["significant"]
            and r["vs_best_ci_low"] <= 0.0 <= r["vs_best_ci_high"]]


# --------------------------------------------------------------------------------------
# the search
# --------------------------------------------------------------------------------------


def search(
    keys: pd.DataFrame,
    real: pd.DataFrame,
    simulate: Simulator,
    settings: SearchSettings | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    fit_keys: pd.DataFrame | None = None,
) -> SearchResult:
    """Find the effects that explain the gap between ``real`` and the simulation.

    Parameters
    ----------
    keys : DataFrame
        The pulses to simulate (one row per real pulse): at least dataset, sample_id,
        species, plus whatever ``simulate`` needs. The significance of the base model's gap,
        the test of each candidate and the residual use all of them.
    real : DataFrame
        Real feature table of those pulses (dataset, sample_id, species, features; with
        pulse_id when ``fit_keys`` is given).
    simulate : Simulator
        ``simulate(pulses, effects, seed) -> feature table`` (:data:`Simulator`).
    settings : SearchSettings, optional
    seed : int
        Master seed: split, simulation seeds and bootstrap draws derive from it.
    progress : callable, optional
        Called with a label after each new simulation.
    fit_keys : DataFrame, optional
        The subset of ``keys`` (dataset, pulse_id) on which candidates are fitted (step 2 of
        the module docstring), default all of them. Fitting takes ~8 simulations per
        candidate and half, testing 1: a subset keeps the fits cheap while the test, which
        decides what is named, sees every pulse.

    Returns
    -------
    SearchResult
    """
    settings = settings or SearchSettings()
    for col in ("dataset", "sample_id", "species"):
        if col not in keys.columns:
            raise WaveforestError(f"diagnose: pulse table lacks column {col!r}")
    keys = keys.assign(sample_id=keys["sample_id"].astype(str))
    real = real.assign(sample_id=real["sample_id"].astype(str))
    s_split, s_a, s_b, s_wa, s_wb, s_all = np.random.SeedSequence(seed).generate_state(6)
    ids = dict(zip(HALVES, split_samples(keys, s_split)))
    if not ids["A"] and not ids["B"]:
        raise WaveforestError("diagnose: no field sample to diagnose")
    sim_seeds = {"A": int(s_a), "B": int(s_b)}

    def halves_of(pulses: pd.DataFrame, real_rows: pd.DataFrame):
        by_half = {h: pulses[pulses["sample_id"].isin(ids[h])].reset_index(drop=True) for h in HALVES}
        out = {}
        for h, s_w in zip(HALVES, (s_wa, s_wb)):
            uni = _gap.sample_universe(by_half[h])
            out[h] = _Half(real=real_rows[real_rows["sample_id"].isin(uni.index)], universe=uni,
                           weights=_gap.bootstrap_weights(uni, settings.n_boot, s_w))
        return out, _Simulations(simulate, by_half, sim_seeds, settings.replicates, progress)

    test_halves, test_sims = halves_of(keys, real)
    if fit_keys is None:
        halves, sims = test_halves, test_sims
    else:
        on = ["dataset", "pulse_id"]
        fk = fit_keys[on].astype({"dataset": str})
        fit_real = real.astype({"dataset": str}).merge(fk, on=on, how="inner")
        fit = keys.astype({"dataset": str}).merge(fk, on=on, how="inner")
        if len(fit) != len(fk):
            raise WaveforestError("diagnose: fit pulses that are not among the tested pulses")
        halves, sims = halves_of(fit, fit_real)
    ctx = _Context(halves, sims, settings, test_halves, test_sims)
    tested = [t for _, t in settings.folds]
    df = _gap.cluster_df(pd.concat([test_halves[t].universe for t in tested]))

    def report(effects: dict) -> _gap.GapReport:
        return _gap.gap_report(real, test_sims.all(effects), n_boot=settings.n_boot, seed=s_all,
                               alpha=settings.alpha, wasserstein=False, **settings.gap_kw)

    baseline = report({})
    current: dict[str, float] = {}
    named: list[NamedEffect] = []
    rows, curves = [], []
    reason = ""
    thin = [h for h in HALVES
            if not ids[h] or not ctx.data(h, {}).valid.any() or not ctx.test_data(h, {}).valid.any()]
    rounds = settings.rounds
    if not baseline.significant:  # nothing to explain: no search (and no spurious candidate)
        rounds = 0
        reason = "the base model's gap is within the noise floor"
    elif thin:
        rounds = 0
        reason = (f"half {thin[0]} of the field samples has no dataset x species cell with at least "
                  f"{settings.min_pulses} pulses from {settings.min_samples} samples: too few field samples "
                  "to fit and test candidates on separate halves")
    for rnd in range(1, rounds + 1):
        # effects that keep the plants first: they share the current model's cached scenes
        todo = sorted((c for c in settings.candidates if c not in current), key=lambda c: not cat.reuses_vegetation(c))
        if not todo:
            reason = "every candidate is in the model"
            break
        results: list[Candidate] = []
        for name in todo:
            est, fits = _fit(name, current, ctx)
            for f in fits:
                curves += [{"round": rnd, "name": name, "half": f.half, "u": u, "value": cat.from_u(name, u),
                            "gap": g} for u, g in zip(f.u, f.gap)]
            tested_models = [cat.with_effect(current, name, cat.from_u(name, f.u_hat)) for f in fits]
            gb, gn, excess, red, reps = _test(current, tested_models, ctx)
            lo, hi = _gap.wald_interval(red, reps, df, settings.alpha)
            rel = red / excess if excess > 0 else math.nan
            sig = bool(lo > 0 and rel >= settings.min_relative_reduction and est.excludes_off)
            results.append(Candidate(round=rnd, estimate=est, gap_base=gb, gap_new=gn, excess_base=excess,
                                     reduction=red, reduction_ci_low=float(lo), reduction_ci_high=float(hi),
                                     relative=float(rel), significant=sig, replicates=reps))
        order = np.argsort([-c.reduction for c in results], kind="stable")
        inside = [i for i in order if not at_bound(results[i].estimate.name, results[i].estimate.u_hat)]
        best = results[inside[0] if inside else order[0]]
        round_rows = []
        for rank, i in enumerate(order, start=1):
            c = results[i]
            dlo, dhi = _gap.wald_interval(best.reduction - c.reduction, best.replicates - c.replicates,
                                          df, settings.alpha)
            round_rows.append({**c.row(), "rank": rank, "vs_best_ci_low": float(dlo), "vs_best_ci_high": float(dhi)})
        rows += round_rows
        if not inside:
            reason = f"round {rnd}: every candidate's fit lies at the edge of its range"
            break
        pinned = [results[i].estimate.name for i in order[:list(order).index(inside[0])]]  # ranked above best
        edge = (f" ({', '.join(pinned)} reduce{'s' if len(pinned) == 1 else ''} it more, but only with a fit at "
                "the edge of the range)") if pinned else ""
        alike = look_alikes(round_rows, best.estimate.name)
        if not best.significant:
            alike_note = (f"; {', '.join(alike)} reduce{'s' if len(alike) == 1 else ''} it significantly, but "
                          "not distinguishably from it (look-alikes these data cannot tell apart)") if alike else ""
            b = best.estimate
            why = (f"reduces the gap, but its fitted value's interval [{b.ci_low:.3g}, {b.ci_high:.3g}] includes "
                   f"the off value {cat.effect(b.name).off:g}" if best.reduction_ci_low > 0 and not b.excludes_off
                   else "does not reduce the gap significantly")
            reason = f"round {rnd}: the best candidate ({b.name}) {why}" + edge + alike_note
            break
        win = best
        e = win.estimate
        current = cat.with_effect(current, e.name, e.value)
        named.append(NamedEffect(name=e.name, value=e.value, ci_low=e.ci_low, ci_high=e.ci_high,
                                 gap_reduction=win.reduction, reduction_ci_low=win.reduction_ci_low,
                                 reduction_ci_high=win.reduction_ci_high, relative_reduction=win.relative,
                                 round=rnd, look_alikes=alike))
        if settings.refit and len(named) > 1:
            current = _refit(named, current, ctx)
        if not report(current).significant:
            reason = f"round {rnd}: the remaining gap is within the noise floor"
            break
        if rnd == settings.rounds:
            reason = f"the most rounds ({settings.rounds}) were run"
    residual = report(current)
    if not baseline.significant:
        verdict = "none"
    elif named:
        verdict = "named"
    else:
        verdict = "unexplained"
    return SearchResult(
        verdict=verdict, named=named, candidates=pd.DataFrame(rows), curves=pd.DataFrame(curves),
        baseline=baseline, residual=residual, reason=reason,
        n_simulations=sims.calls + (test_sims.calls if test_sims is not sims else 0), halves=ids,
        simulations=sims, test_simulations=test_sims,
    )
