"""The search: which missing effect explains the gap, at what value, and how sure are we.

docs/method.md §(j) (the search). Procedure (one *round*; :func:`search` runs up to ``rounds``):

1. **Split.** The field samples of every species are split at random into halves A and B
   (:func:`split_samples`; all pulses of a sample, in every dataset, go to the same half).
   The split is drawn once and kept for every round. Each half has its own simulation seed.
2. **Fit** each candidate effect not yet in the model on one half (:func:`fit_candidate`):
   simulate that half's fit pulses (all, or the subset ``fit_keys``) with the current model
   plus the candidate at each value of a grid over its search coordinate
   (:func:`.catalogue.grid`, always containing "off" = the current model), then refine with
   a few Brent-like steps (:func:`.optimise.refinement_step`). Every value uses the **same
   seed** (common random numbers, :class:`.replicate_cache.SimulationCache`). The fitted value
   minimises the gap G(u) (:func:`.optimise.parabolic_vertex`); its interval: the same
   cluster-bootstrap resamples applied to every simulated value give a gap curve per
   replicate, whose parabolic minimum is a replicate of the fitted value.
3. **Test** the fitted candidate on all pulses of the *other* half: the reduction
   R = G_current - G_candidate with a paired cluster bootstrap. With ``crossfit`` the roles
   are swapped too and both fits and both reductions are averaged. A candidate is
   *significant* when R's interval (:func:`reduction_interval`: a Wald interval on
   log(G_current / G_candidate), as a large reduction's replicates skew) lies above 0,
   R >= ``min_relative_reduction`` x the current excess gap on the tested samples (x their
   gap when their own floor reaches it), and the fitted value's interval excludes the
   effect's off value. No multiplicity correction over the candidates.
4. **Name** the candidate with the largest R fitted inside its range (:func:`at_bound`) if
   it is significant; candidates ranked above it with a fit at the bound are reported, not
   named, and so are significant candidates not told apart from it (:func:`look_alikes`).
   If it is not significant, a significant fit at the bound whose interval reaches well into
   the range (not :func:`pinned`) is named instead.
5. **Along the signatures.** When step 4 names nothing and the search has the signature test
   (:mod:`.signature_test`), the test reads the current model on all samples; if it fires,
   each candidate it reads above its threshold is fitted along its signature on the round's
   grid simulations (:mod:`.signature_fit`: where the test's statistic crosses 0, with a
   bootstrap interval), and the one that explains the evidence (inside its range, interval
   excluding off; at the fitted value the test silent and at least half the terms' excess
   evidence gone) is named: the gap's half-sample fit can miss an effect that the signature
   test reads on all samples. Other candidates that explain it too are its look-alikes. An
   effect named so keeps its value in the re-fits.

   From the second effect on, re-fit all named effects by coordinate descent
   (:data:`REFIT_PASSES`). Stop when nothing is named, when ``rounds`` effects are named,
   or when the model's gap is within the noise floor.

Verdict (:data:`waveforest.io.results.VERDICTS`): ``none`` when the base model's gap is not significant
above its noise floor; ``named`` when at least one effect was named; ``inconclusive`` when a
half of the field samples is too thin to fit and test a candidate on; ``unexplained``
otherwise. Gaps are in squared pooled SDs; search coordinates u in [0, 1]. Errors:
:class:`waveforest.errors.WaveforestError` for a pulse table without dataset, sample_id or
species, no field sample, or fit pulses outside the tested pulses. Measured behaviour
(look-alikes, fits at a bound): docs/validation.md, Diagnose.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd
from scipy.stats import chi2

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import (
    DEFAULT_FEATURES,
    MIN_CELL_PULSES,
    MIN_CELL_SAMPLES,
    GapData,
    GapReport,
    gap_report,
    sample_universe,
    total_gap,
    total_noise_floor,
)
from waveforest.diagnose.optimise import parabolic_vertex, refinement_step
from waveforest.diagnose.replicate_cache import HALVES, SimulationCache, Simulator
from waveforest.diagnose.signature_fit import EXPLAINED_SHARE, common_terms, explained, fit_along, terms_at
from waveforest.diagnose.signature_test import ALPHA as SIGNATURE_ALPHA
from waveforest.diagnose.signature_test import SignatureTest, terms
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.model.forward import drift_dof
from waveforest.rng import named_generator, named_seeds
from waveforest.stats.bootstrap import DEFAULT_ALPHA, bootstrap_weights, cluster_df, wald_interval

REFIT_PASSES = 3
"""Most coordinate-descent passes over the named effects after a new one is named."""

_REFIT_TOL_U = 0.01
"""A pass that moves no named effect by more than this (search coordinate) ends the re-fit."""


@dataclass(frozen=True)
class SearchSettings:
    """Settings of the search (config section ``diagnose``; defaults are the schema's).

    Attributes
    ----------
    rounds : int
        Most effects named.
    n_boot : int
        Cluster-bootstrap replicates (``bootstrap``).
    values : int
        Grid values per candidate (including "off").
    refine : int
        Refinement steps per candidate fit (one simulation each).
    replicates : int
        Simulated pulses per real pulse and value (``pulses_per_value``).
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
        Gap settings (:meth:`.gap.GapData.build`; ``min_cell_pulses``, ``min_cell_samples``).
    floor_scale : float
        Factor on every noise floor (:meth:`.gap.GapData.build`), calibrated by the diagnosis
        (:func:`.power.floor_calibration`); not a config key.
    signature_alpha : float or None
        Family-wise false-alarm rate of the signature test (:mod:`.signature_test`), which the
        power analysis builds and the diagnosis applies to the base model; None: no signature test.
    """

    rounds: int = 3
    n_boot: int = 200
    values: int = 5
    refine: int = 3
    replicates: int = 1
    alpha: float = DEFAULT_ALPHA
    min_relative_reduction: float = 0.2
    candidates: tuple[str, ...] = tuple(CATALOGUE)
    refit: bool = True
    crossfit: bool = True
    features: tuple[str, ...] = DEFAULT_FEATURES
    floors: dict | None = None
    min_pulses: int = MIN_CELL_PULSES
    min_samples: int = MIN_CELL_SAMPLES
    floor_scale: float = 1.0
    signature_alpha: float | None = SIGNATURE_ALPHA

    def __post_init__(self) -> None:
        for name in self.candidates:
            cat.effect(name)
        if self.rounds < 1 or self.values < 3 or self.refine < 0 or self.replicates < 1 or self.n_boot < 10:
            raise WaveforestError(
                "diagnose: need rounds >= 1, values >= 3, refine >= 0, pulses_per_value >= 1, bootstrap >= 10"
            )
        if not 0 < self.alpha < 1:
            raise WaveforestError(f"diagnose.alpha must be in (0, 1), got {self.alpha}")
        if self.signature_alpha is not None and not 0 < self.signature_alpha < 1:
            raise WaveforestError(f"diagnose.signature_alpha must be in (0, 1) or null, got {self.signature_alpha}")

    @property
    def gap_kw(self) -> dict:
        """Keyword arguments of :meth:`.gap.GapData.build`."""
        return {"features": self.features, "floors": self.floors,
                "min_pulses": self.min_pulses, "min_samples": self.min_samples, "floor_scale": self.floor_scale}

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
        return cls.of(fits[0].name, float(np.mean([f.u_hat for f in fits])),
                      np.mean([f.u_boot for f in fits], axis=0), alpha)

    @classmethod
    def of(cls, name: str, u_hat: float, u_boot: np.ndarray, alpha: float) -> Estimate:
        """The fit ``u_hat`` with the percentile interval of its replicates ``u_boot`` (B,)."""
        u_b = u_boot[np.isfinite(u_boot)]
        lo, hi = np.quantile(u_b, [alpha / 2, 1 - alpha / 2]) if u_b.size else (u_hat, u_hat)
        v_lo, v_hi = cat.value_interval(name, lo, hi)
        return cls(name=name, u_hat=u_hat, value=cat.from_u(name, u_hat), ci_low=v_lo, ci_high=v_hi,
                   u_low=float(lo), u_high=float(hi))

    def with_drift_realization(self, dof: float, alpha: float) -> Estimate:
        """The value's interval as one of the SD of a drift process (:data:`DRIFT_EFFECTS`).

        The fit measures the RMS of the drift the data hold, ``dof`` independent values of it
        (:func:`.model.forward.drift_dof`, both axes): given that RMS s, the process SD lies in
        s [sqrt(ν / chi^2_(1-alpha/2, ν)), sqrt(ν / chi^2_(alpha/2, ν))]. The half-widths of
        that interval and of the fit's add in quadrature on log(value). ``u_low``/``u_high``
        stay the fit's: whether the effect is there is the fit's question.
        """
        if not (dof > 0 and self.value > 0):
            return self
        q_lo, q_hi = np.sqrt(dof / chi2.ppf([1 - alpha / 2, alpha / 2], dof))
        fit_down = math.log(max(self.value / self.ci_low, 1.0)) if self.ci_low > 0 else math.inf
        down = math.hypot(fit_down, math.log(q_lo))
        up = math.hypot(math.log(max(self.ci_high / self.value, 1.0)), math.log(q_hi))
        top = cat.from_u(self.name, 1.0)
        return replace(self, ci_low=self.value * math.exp(-down), ci_high=min(self.value * math.exp(up), top))


SIGNATURE_REFINE = 2
"""Simulations of a fit along a signature at its last crossing (step 5), each interpolated anew."""

DRIFT_EFFECTS = ("xy_error",)
"""Effects that are the SD of a random process of which the compared pulses hold few
independent values: the georeferencing drift (:func:`.model.forward.georeferencing_drift`)
changes over seconds, so a few passes hold a few dozen. Their intervals also carry the spread
of the realized drift around the process SD (:meth:`Estimate.with_drift_realization`)."""


AT_BOUND_U = 0.02
"""A fit within this distance (search coordinate, 0 ... 1 over the bounds) of the bound
that is not the effect's off value is *at the bound*."""


def at_bound(name: str, u_hat: float) -> bool:
    """Whether a fit lies at the far edge of the effect's range (:data:`AT_BOUND_U`)."""
    u0 = cat.off_u(name)
    return bool((u_hat <= AT_BOUND_U and u0 > AT_BOUND_U) or (u_hat >= 1 - AT_BOUND_U and u0 < 1 - AT_BOUND_U))


PINNED_U = 0.25
"""A fit at the bound whose interval's inner end also lies within this distance (search
coordinate) of that bound is *pinned*."""


def pinned(e: Estimate) -> bool:
    """Whether a fit at the bound is pinned there (:data:`PINNED_U`): the data then ask for a
    value at or beyond the edge of what the catalogue deems plausible, the mark of a look-alike.
    A fit at the bound whose interval reaches further in is not: these data cannot tell that
    part of the range from its edge (an effect whose signature saturates)."""
    if not at_bound(e.name, e.u_hat):
        return False
    return bool(e.u_low >= 1 - PINNED_U) if e.u_hat > 0.5 else bool(e.u_high <= PINNED_U)


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
    along_signature: str = ""
    """Empty when the gap named it; else the evidence of its fit along the signature (step 5
    of the module docstring), in words."""


@dataclass
class SearchResult:
    """Everything the search found.

    Attributes
    ----------
    verdict : str
        ``none``, ``named``, ``inconclusive`` (halves too thin to try a candidate) or ``unexplained``.
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
    simulations, test_simulations : SimulationCache
        The caches of every simulation run on the fit pulses and on the tested pulses (the
        same object when all pulses are fitted); ``.all(effects)`` gives all samples under
        a model, simulating only what is not cached.
    signature : dict or None
        The signature test's reading of the base model (:meth:`.signature_test.SignatureTest.read`),
        set by :func:`.missing_effects.find_missing_effects`; None without one.
    """

    verdict: str
    named: list[NamedEffect]
    candidates: pd.DataFrame
    curves: pd.DataFrame
    baseline: GapReport
    residual: GapReport
    reason: str
    n_simulations: int
    halves: dict
    simulations: SimulationCache = field(default=None, repr=False)
    test_simulations: SimulationCache = field(default=None, repr=False)
    signature: dict | None = None

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
    uni = sample_universe(keys)
    seen = keys.assign(sample_id=keys["sample_id"].astype(str), dataset=keys["dataset"].astype(str))
    seen = seen.groupby("sample_id")["dataset"].agg(lambda d: ",".join(sorted(set(d))))
    stratum = uni.astype(str) + "|" + seen.reindex(uni.index).fillna("").astype(str)
    rng = named_generator("search_split", seed)
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



@dataclass
class _Half:
    real: pd.DataFrame
    universe: pd.Series
    weights: np.ndarray


class _Context:
    """What every step of one search shares: halves, simulations, settings.

    ``halves``/``sims`` hold the fit pulses of each half, ``test_halves``/``test_sims`` the
    tested pulses (the same objects when every pulse is fitted); ``signature`` the signature
    test and ``everything`` the real rows, universe and bootstrap weights of all tested samples
    it reads (step 5 of the module docstring; None without it).
    """

    def __init__(self, halves: dict[str, _Half], sims: SimulationCache, settings: SearchSettings,
                 test_halves: dict[str, _Half] | None = None, test_sims: SimulationCache | None = None,
                 drift_dof: float = 0.0, signature: SignatureTest | None = None, everything: _Half | None = None):
        self.halves = halves
        self.signature, self.everything = signature, everything
        self.drift_dof = drift_dof
        self.sims = sims
        self.settings = settings
        self.test_halves = halves if test_halves is None else test_halves
        self.test_sims = sims if test_sims is None else test_sims

    def data(self, half: str, effects: dict) -> GapData:
        """Gap data of the fit pulses of ``half`` under ``effects``."""
        h = self.halves[half]
        return GapData.build(h.real, self.sims.get(half, effects), h.universe, **self.settings.gap_kw)

    def test_data(self, half: str, effects: dict) -> GapData:
        """Gap data of the tested pulses of ``half`` under ``effects``."""
        h = self.test_halves[half]
        return GapData.build(h.real, self.test_sims.get(half, effects), h.universe, **self.settings.gap_kw)


# --------------------------------------------------------------------------------------
# fit and test of one candidate
# --------------------------------------------------------------------------------------


def _model_at(name: str, u: float, current: dict[str, float]) -> dict[str, float]:
    """``current`` with ``name`` at search coordinate ``u`` (removed at its off value)."""
    others = {k: v for k, v in current.items() if k != name}
    return others if abs(u - cat.off_u(name)) < 1e-12 else cat.with_effect(others, name, cat.from_u(name, u))


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

    def data_at(u: float) -> GapData:
        return ctx.data(half, _model_at(name, u, current))

    us = list(cat.grid(name, settings.values))
    datas = [data_at(u) for u in us]
    for _ in range(settings.refine):
        valid = np.logical_and.reduce([d.valid for d in datas])
        order = np.argsort(us)
        g = np.array([total_gap(datas[i], valid=valid) for i in order])
        v = refinement_step(np.asarray(us)[order], g)
        if v is None:
            break
        us.append(v)
        datas.append(data_at(v))
    order = np.argsort(us)
    u_arr = np.asarray(us)[order]
    datas = [datas[i] for i in order]
    valid = np.logical_and.reduce([d.valid for d in datas])
    g = np.array([total_gap(d, valid=valid) for d in datas])
    w = ctx.halves[half].weights
    reps = np.stack([total_gap(d, w, valid) for d in datas], axis=1)  # (B, k)
    return Fit(name=name, half=half, u=u_arr, gap=g, u_hat=float(parabolic_vertex(u_arr, g)),
               u_boot=parabolic_vertex(u_arr, reps))


def _fit(name: str, current: dict, ctx: _Context) -> tuple[Estimate, list[Fit]]:
    fits = [fit_candidate(name, current, ctx, f) for f, _ in ctx.settings.folds]
    est = Estimate.combine(fits, ctx.settings.alpha)
    if name in DRIFT_EFFECTS:
        est = est.with_drift_realization(ctx.drift_dof, ctx.settings.alpha)
    return est, fits


def _test(current: dict, models_by_fold: list[dict], ctx: _Context):
    """The gaps on the test halves: (gap_base, gap_new, excess of gap_base over its floor, and the
    bootstrap replicates (B,) of gap_base and of gap_new).

    ``models_by_fold[k]`` is the model tested on fold k's test half (with fold k's fit).
    """
    gb, gn, ex, rep_b, rep_n = [], [], [], [], []
    for (_, t), eff in zip(ctx.settings.folds, models_by_fold):
        base, cand = ctx.test_data(t, current), ctx.test_data(t, eff)
        valid = base.valid & cand.valid
        w = ctx.test_halves[t].weights
        gb.append(total_gap(base, valid=valid))
        gn.append(total_gap(cand, valid=valid))
        ex.append(gb[-1] - total_noise_floor(base, w, valid))
        rep_b.append(total_gap(base, w, valid))
        rep_n.append(total_gap(cand, w, valid))
    # folds test disjoint halves with independent resamples: replicate-wise mean is a replicate of the mean
    return (float(np.mean(gb)), float(np.mean(gn)), float(np.mean(ex)), np.mean(rep_b, axis=0),
            np.mean(rep_n, axis=0))


def reduction_interval(gap_base: float, gap_new: float, reps_base: np.ndarray, reps_new: np.ndarray, df: int,
                       alpha: float) -> tuple[float, float]:
    """Interval of R = G_base - G_new from paired bootstrap replicates (B,) of both gaps.

    A gap is a sum of squares whose replicates skew right as it grows, and so does a large
    reduction's: a symmetric interval R -+ t SE* then reaches below 0 though every replicate
    lies above it. The Wald interval (:func:`wald_interval`, t with ``df``) is taken on
    log(G_base / G_new), near symmetric whatever the effect's size, and mapped back through
    R = G_base (1 - G_new / G_base); with a gap or too many replicates at 0 or NaN, on R itself.
    """
    ok = np.isfinite(reps_base) & np.isfinite(reps_new) & (reps_base > 0) & (reps_new > 0)
    if gap_base > 0 and gap_new > 0 and ok.sum() >= max(10, ok.size // 2):
        log_ratio = np.log(reps_base[ok] / reps_new[ok])
        lo, hi = wald_interval(np.log(gap_base / gap_new), log_ratio, df, alpha)
        return float(gap_base * (1 - np.exp(-lo))), float(gap_base * (1 - np.exp(-hi)))
    lo, hi = wald_interval(gap_base - gap_new, reps_base - reps_new, df, alpha)
    return float(lo), float(hi)


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
            if e.along_signature:  # the gap's fit is what missed it
                continue
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


@dataclass
class _State:
    """What the rounds of one search build up."""

    reason: str = ""
    current: dict = field(default_factory=dict)
    named: list = field(default_factory=list)
    rows: list = field(default_factory=list)
    curves: list = field(default_factory=list)


def _halves_of(pulses: pd.DataFrame, real_rows: pd.DataFrame, ids: dict, sim_seeds: dict, weight_seeds: dict,
               simulate: Simulator, settings: SearchSettings, progress) -> tuple[dict, SimulationCache]:
    """The halves (real rows, universe, bootstrap weights) of ``pulses`` and their simulation cache."""
    by_half = {h: pulses[pulses["sample_id"].isin(ids[h])].reset_index(drop=True) for h in HALVES}
    out = {}
    for h in HALVES:
        uni = sample_universe(by_half[h])
        out[h] = _Half(real=real_rows[real_rows["sample_id"].isin(uni.index)], universe=uni,
                       weights=bootstrap_weights(uni, settings.n_boot, weight_seeds[h]))
    return out, SimulationCache(simulate, by_half, sim_seeds, settings.replicates, progress)


def _drift_values(keys: pd.DataFrame) -> float:
    """ν of :meth:`Estimate.with_drift_realization` for the pulses ``keys`` (0 without gps_time).

    The real drift runs on through a dataset's passes; the twins draw theirs afresh per field
    sample (:func:`.model.forward.georeferencing_drift` over one (sample, instance) group).
    The fitted value is the ratio of the two realized RMS, so the log-variances 1 / (2 ν) of
    both add: ν = 1 / (1 / ν_real + 1 / ν_twins), each over both axes.
    """
    if "gps_time" not in keys.columns:
        return 0.0
    t, ds = keys["gps_time"].to_numpy(np.float64), keys["dataset"].astype(str)
    real, twins = 2.0 * drift_dof(t, ds.to_numpy()), 2.0 * drift_dof(t, (ds + "/" + keys["sample_id"]).to_numpy())
    return 1.0 / (1.0 / real + 1.0 / twins) if real > 0 and twins > 0 else 0.0


def _setup(keys: pd.DataFrame, real: pd.DataFrame, simulate: Simulator, settings: SearchSettings, seed: int,
           progress, fit_keys: pd.DataFrame | None, signature: SignatureTest | None = None):
    """Split, seeds, halves and caches of a search: (context, halves' sample ids, report, df).

    ``report(effects)`` is the gap on all tested pulses under ``effects``; ``df`` the degrees
    of freedom of a reduction on the tested halves.
    """
    for col in ("dataset", "sample_id", "species"):
        if col not in keys.columns:
            raise WaveforestError(f"diagnose: pulse table lacks column {col!r}")
    keys = keys.assign(sample_id=keys["sample_id"].astype(str))
    real = real.assign(sample_id=real["sample_id"].astype(str))
    s_split, s_a, s_b, s_wa, s_wb, s_all, s_sig = named_seeds("search", seed, n=7)
    ids = dict(zip(HALVES, split_samples(keys, s_split)))
    if not ids["A"] and not ids["B"]:
        raise WaveforestError("diagnose: no field sample to diagnose")
    seeds = ({"A": int(s_a), "B": int(s_b)}, {"A": s_wa, "B": s_wb})
    test_halves, test_sims = _halves_of(keys, real, ids, *seeds, simulate, settings, progress)
    if fit_keys is None:
        halves, sims = test_halves, test_sims
    else:
        on = ["dataset", "pulse_id"]
        fk = fit_keys[on].astype({"dataset": str})
        fit_real = real.astype({"dataset": str}).merge(fk, on=on, how="inner")
        fit = keys.astype({"dataset": str}).merge(fk, on=on, how="inner")
        if len(fit) != len(fk):
            raise WaveforestError("diagnose: fit pulses that are not among the tested pulses")
        halves, sims = _halves_of(fit, fit_real, ids, *seeds, simulate, settings, progress)
    everything = None
    if signature is not None:
        uni = sample_universe(keys)
        everything = _Half(real=real, universe=uni,
                           weights=bootstrap_weights(uni, settings.n_boot, s_sig))
    ctx = _Context(halves, sims, settings, test_halves, test_sims, _drift_values(keys), signature, everything)
    df = cluster_df(pd.concat([test_halves[t].universe for _, t in settings.folds]))

    def report(effects: dict) -> GapReport:
        return gap_report(real, test_sims.all(effects), n_boot=settings.n_boot, seed=s_all,
                          alpha=settings.alpha, wasserstein=False, **settings.gap_kw)

    return ctx, ids, report, df


def _reason_not_to_search(significant: bool, ctx: _Context, ids: dict) -> str:
    """Why no round is run (empty when the rounds run): no significant gap, or a half too thin."""
    s = ctx.settings
    thin = [h for h in HALVES
            if not ids[h] or not ctx.data(h, {}).valid.any() or not ctx.test_data(h, {}).valid.any()]
    if not significant:  # nothing to explain: no search (and no spurious candidate)
        return "the base model's gap is within the noise floor"
    if thin:
        return (f"half {thin[0]} of the field samples has no dataset x species cell with at least "
                f"{s.min_pulses} pulses from {s.min_samples} samples: too few field samples "
                "to fit and test candidates on separate halves")
    return ""


def _evaluate(rnd: int, name: str, state: _State, ctx: _Context, df: int) -> Candidate:
    """Fit ``name`` on the fit halves, test it on the other halves; its curves go to ``state``."""
    settings, current = ctx.settings, state.current
    est, fits = _fit(name, current, ctx)
    for f in fits:
        state.curves += [{"round": rnd, "name": name, "half": f.half, "u": u, "value": cat.from_u(name, u),
                          "gap": g} for u, g in zip(f.u, f.gap)]
    tested_models = [cat.with_effect(current, name, cat.from_u(name, f.u_hat)) for f in fits]
    gb, gn, excess, reps_b, reps_n = _test(current, tested_models, ctx)
    red, reps = gb - gn, reps_b - reps_n
    lo, hi = reduction_interval(gb, gn, reps_b, reps_n, df, settings.alpha)
    # the share of the tested halves' excess removed; halves whose own floor reaches their gap
    # (thin cells) have no excess to share: the share of their gap
    rel = red / excess if excess > 0 else (red / gb if gb > 0 else math.nan)
    sig = bool(lo > 0 and rel >= settings.min_relative_reduction and est.excludes_off)
    return Candidate(round=rnd, estimate=est, gap_base=gb, gap_new=gn, excess_base=excess,
                     reduction=red, reduction_ci_low=float(lo), reduction_ci_high=float(hi),
                     relative=float(rel), significant=sig, replicates=reps)


def _rank(results: list[Candidate], df: int, alpha: float):
    """(order by reduction, the ranked indices fitted inside their range, best, ``candidates.csv`` rows).

    The best is the first fitted inside its range; if that is not significant, the first
    significant fit at the bound that is not :func:`pinned` stands in for it."""
    order = np.argsort([-c.reduction for c in results], kind="stable")
    inside = [i for i in order if not at_bound(results[i].estimate.name, results[i].estimate.u_hat)]
    best = results[inside[0] if inside else order[0]]
    if not best.significant:
        broad = [i for i in order if i not in inside and results[i].significant and not pinned(results[i].estimate)]
        best = results[broad[0]] if broad else best
    rows = []
    for rank, i in enumerate(order, start=1):
        c = results[i]
        dlo, dhi = wald_interval(best.reduction - c.reduction, best.replicates - c.replicates, df, alpha)
        rows.append({**c.row(), "rank": rank, "vs_best_ci_low": float(dlo), "vs_best_ci_high": float(dhi)})
    return order, inside, best, rows


def _not_named_reason(rnd: int, results: list[Candidate], order, inside: list, best: Candidate,
                      alike: list[str]) -> str:
    """Why the best candidate of round ``rnd`` is not named (it is not significant)."""
    pinned = [results[i].estimate.name for i in order[:list(order).index(inside[0])]]  # ranked above best
    edge = (f" ({', '.join(pinned)} reduce{'s' if len(pinned) == 1 else ''} it more, but only with a fit at "
            "the edge of the range)") if pinned else ""
    alike_note = (f"; {', '.join(alike)} reduce{'s' if len(alike) == 1 else ''} it significantly, but "
                  "not distinguishably from it (look-alikes these data cannot tell apart)") if alike else ""
    b = best.estimate
    why = (f"reduces the gap, but its fitted value's interval [{b.ci_low:.3g}, {b.ci_high:.3g}] includes "
           f"the off value {cat.effect(b.name).off:g}" if best.reduction_ci_low > 0 and not b.excludes_off
           else "does not reduce the gap significantly")
    return f"round {rnd}: the best candidate ({b.name}) {why}" + edge + alike_note


def _fit_along_signature(name: str, current: dict, ctx: _Context, terms_of) -> tuple[Estimate | None, str, tuple]:
    """One candidate's fit along its signature on the round's grid, refined by
    :data:`SIGNATURE_REFINE` simulations at its crossing: (estimate or None without crossing,
    why it does not explain the evidence or "", (reading there, share of the evidence gone))."""
    test, s = ctx.signature, ctx.settings
    u = list(cat.grid(name, s.values))
    found = [terms_of(_model_at(name, v, current)) for v in u]
    for step in range(SIGNATURE_REFINE + 1):
        order = np.argsort(u)
        x, xb, index = common_terms([found[i][0] for i in order], [found[i][1] for i in order])
        grid = np.asarray(u)[order]
        u_hat, u_boot = fit_along(test, name, grid, x, xb, index, cat.off_u(name))
        if step == SIGNATURE_REFINE or not math.isfinite(u_hat) or np.min(np.abs(grid - u_hat)) < 1e-3:
            break
        u.append(u_hat)
        found.append(terms_of(_model_at(name, u_hat, current)))
    if not math.isfinite(u_hat):
        return None, "no crossing in its range", ()
    est = Estimate.of(name, u_hat, u_boot, s.alpha)
    if name in DRIFT_EFFECTS:
        est = est.with_drift_realization(ctx.drift_dof, s.alpha)
    off = int(np.argmin(np.abs(grid - cat.off_u(name))))
    ok, after, share = explained(test, pd.Series(x[off], index=index), terms_at(u_hat, grid, x, xb, index))
    why = ("at the edge of its range" if at_bound(name, u_hat) else
           "its interval includes off" if not est.excludes_off else
           f"the test still fires there: {after['margin'] + after['threshold']:.3g} ({after['effect']})"
           if after["fires"] else
           "" if ok else f"it removes {share:.0%} of the evidence, less than {EXPLAINED_SHARE:.0%}")
    return est, why, (after, share)


def _named_along_signature(rnd: int, results: list[Candidate], state: _State,
                           ctx: _Context) -> tuple[NamedEffect | None, str]:
    """Step 5 of the module docstring: (the effect named along its signature or None, why not in words).

    On all tested samples, with the round's grid simulations (only when every pulse is fitted):
    the signature test's reading of the current model; when it fires, every candidate of the
    round whose |z| / c is above the threshold is fitted along its signature
    (:func:`_fit_along_signature`). Of those that explain the evidence, the one read lowest at
    its fit is named, the others are its look-alikes."""
    test, s, every = ctx.signature, ctx.settings, ctx.everything
    if test is None or every is None or ctx.sims is not ctx.test_sims:
        return None, ""
    kw = {"floors": s.floors, "min_pulses": s.min_pulses, "min_samples": s.min_samples}

    def terms_of(effects: dict) -> tuple[pd.Series, np.ndarray]:
        return terms(every.real, ctx.sims.all(effects), every.universe, every.weights, **kw)

    now = test.read(*terms_of(state.current))
    if not now["fires"]:
        return None, ""
    by_name = {c.estimate.name: c for c in results}
    ratio = {e: abs(z) / now["scale"][e] for e, z in now["z"].items() if z is not None and e in by_name}
    explains, misses = [], []
    for name in sorted((e for e, r in ratio.items() if r > now["threshold"]), key=ratio.get, reverse=True):
        est, why, found = _fit_along_signature(name, state.current, ctx, terms_of)
        if why:
            misses.append(f"{name}{f' {est.value:.3g}' if est else ''} ({why})")
        else:
            explains.append((found[0]["margin"], est, *found))
    if not explains:
        return None, "; along the signatures, no candidate explains the evidence" + (
            f": {', '.join(misses)}" if misses else "")
    _, est, after, share = min(explains, key=lambda f: f[0])
    c = by_name[est.name]
    text = (f"along its signature: |z| / c {ratio[est.name]:.3g} on the model before it (threshold "
            f"{now['threshold']:.3g}), at {est.value:.3g} the largest |z| / c is "
            f"{after['margin'] + after['threshold']:.3g} ({after['effect']}) and {share:.0%} of the "
            "terms' excess evidence is gone")
    return NamedEffect(name=est.name, value=est.value, ci_low=est.ci_low, ci_high=est.ci_high,
                       gap_reduction=c.reduction, reduction_ci_low=c.reduction_ci_low,
                       reduction_ci_high=c.reduction_ci_high, relative_reduction=c.relative, round=rnd,
                       look_alikes=[f[1].name for f in explains if f[1] is not est],
                       along_signature=text), ""


def _run_round(rnd: int, state: _State, ctx: _Context, df: int, report) -> bool:
    """One round (steps 2-5 of the module docstring); True when the search stops after it."""
    settings = ctx.settings
    # effects that keep the plants first: they share the current model's cached scenes
    todo = sorted((c for c in settings.candidates if c not in state.current),
                  key=lambda c: not cat.reuses_vegetation(c))
    if not todo:
        state.reason = "every candidate is in the model"
        return True
    results = [_evaluate(rnd, name, state, ctx, df) for name in todo]
    order, inside, best, round_rows = _rank(results, df, settings.alpha)
    state.rows += round_rows
    alike = look_alikes(round_rows, best.estimate.name)
    if best.significant and not pinned(best.estimate):
        e = best.estimate
        named = NamedEffect(name=e.name, value=e.value, ci_low=e.ci_low, ci_high=e.ci_high,
                            gap_reduction=best.reduction, reduction_ci_low=best.reduction_ci_low,
                            reduction_ci_high=best.reduction_ci_high, relative_reduction=best.relative,
                            round=rnd, look_alikes=alike)
    else:
        named, misses = _named_along_signature(rnd, results, state, ctx)
        if named is None:
            state.reason = (f"round {rnd}: every candidate's fit lies at the edge of its range" if not inside
                            else _not_named_reason(rnd, results, order, inside, best, alike)) + misses
            return True
    state.current = cat.with_effect(state.current, named.name, named.value)
    state.named.append(named)
    if settings.refit and len(state.named) > 1:
        state.current = _refit(state.named, state.current, ctx)
    if not report(state.current).significant:
        state.reason = f"round {rnd}: the remaining gap is within the noise floor"
        return True
    if rnd == settings.rounds:
        state.reason = f"the most rounds ({settings.rounds}) were run"
    return False


def search(
    keys: pd.DataFrame,
    real: pd.DataFrame,
    simulate: Simulator,
    settings: SearchSettings | None = None,
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
    fit_keys: pd.DataFrame | None = None,
    significant: bool | None = None,
    signature: SignatureTest | None = None,
) -> SearchResult:
    """Find the effects that explain the gap between ``real`` and the simulation.

    Parameters
    ----------
    keys : DataFrame
        The pulses to simulate (one row per real pulse): at least dataset, sample_id,
        species, plus whatever ``simulate`` needs; with gps_time, the intervals of
        :data:`DRIFT_EFFECTS` count the drift values these pulses hold. The significance of
        the base model's gap, the test of each candidate and the residual use all of them.
    real : DataFrame
        Real feature table of those pulses (dataset, sample_id, species, features; with
        pulse_id when ``fit_keys`` is given).
    simulate : Simulator
        ``simulate(pulses, effects, seed) -> feature table`` (:data:`.replicate_cache.Simulator`).
    settings : SearchSettings, optional
    seed : int
        Master seed: split, simulation seeds and bootstrap draws derive from it.
    progress : callable, optional
        Called with a label after each new simulation.
    fit_keys : DataFrame, optional
        The subset of ``keys`` (dataset, pulse_id) on which candidates are fitted (step 2 of
        the module docstring), default all of them: a subset keeps the fits cheap while the
        test, which decides what is named, sees every pulse.
    significant : bool, optional
        Whether the base model's gap lies significantly above its noise floor, decided
        elsewhere (the gap that the diagnosis reports, :func:`.missing_effects.find_missing_effects`);
        default: the search's own baseline. It decides whether rounds run and the verdict ``none``.
    signature : SignatureTest, optional
        The signature test of the power analysis (``real`` then carries the whole waveform's
        statistics): with it, a round whose gap names nothing may name along a signature
        (step 5 of the module docstring).

    Returns
    -------
    SearchResult
    """
    settings = settings or SearchSettings()
    ctx, ids, report, df = _setup(keys, real, simulate, settings, seed, progress, fit_keys, signature)
    baseline = report({})
    significant = baseline.significant if significant is None else bool(significant)
    state = _State(reason=_reason_not_to_search(significant, ctx, ids))
    untried = bool(state.reason)
    if not untried:
        for rnd in range(1, settings.rounds + 1):
            if _run_round(rnd, state, ctx, df, report):
                break
    residual = report(state.current)
    # a gap above the floor with halves too thin to try a candidate: the data cannot tell
    verdict = ("none" if not significant else "named" if state.named else
               "inconclusive" if untried else "unexplained")
    sims, test_sims = ctx.sims, ctx.test_sims
    return SearchResult(
        verdict=verdict, named=state.named, candidates=pd.DataFrame(state.rows), curves=pd.DataFrame(state.curves),
        baseline=baseline, residual=residual, reason=state.reason,
        n_simulations=sims.calls + (test_sims.calls if test_sims is not sims else 0), halves=ids,
        simulations=sims, test_simulations=test_sims,
    )
