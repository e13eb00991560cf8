"""Detection limits: the smallest value of each candidate effect that this data would detect.

docs/method.md §(j) (detection limits). A power analysis on simulated effects, with the
design of the data and the test that decides the verdict ``none``:

* **Pseudo-real data.** The real pulses (``keys``: same pulses, samples and strata) are
  simulated with the candidate at a value v (one twin per pulse, as the real data have one
  record per pulse) and stand in for the measurement; the base model, simulated with another
  seed and ``pulses_per_value`` twins per pulse, is the simulation side.
* **The test.** The two tests that decide whether the diagnosis has a gap to explain, with the
  search's settings and the same cluster bootstrap over field samples: v is *detected* in a
  replicate when the lower bound of the excess gap's interval (:func:`.gap.gap_report`,
  ``alpha``) is above 0, or when the signature test fires (:mod:`.signature_test`, at
  ``signature_alpha``; the candidates' signatures are those of their test values, the pool's
  first seed against the base model's, and the test is calibrated on the replicates without
  effect). Without one of them the search names nothing.
* **Replicates from a pool.** Every model (off and each value) is simulated over all pulses
  with ``pool`` seeds, the same seeds for every model (common random numbers). Replicate r
  draws, for every field sample, the pool member of its pseudo-real pulses and another member
  for its simulation side, and has its own bootstrap weights. Field samples are independent
  clusters (each its own plants, rays and noise), so a data set assembled sample by sample
  from independent simulations is a draw of the same distribution as one simulated whole; the
  replicates share simulations, so they are less independent than ``replicates`` separate
  simulations would be (the Wilson intervals of the power assume independence). Power(v) =
  share of replicates that detect v, with its 95 % Wilson interval.
* **The walk towards the limit.** Per candidate, up to ``values`` strengths on the side of its
  test value (search coordinate u, :mod:`.catalogue`; strength = distance from off). The first
  is the test value itself: whether the data see an effect of that size is a power measured
  there, not an interpolation. If it is detected with power, each next strength is the limit
  estimated from the strengths evaluated so far (below), kept inside the bracket between the
  weakest value detected with power and the strongest one below it that is not (off at the
  start): at most :data:`STEP_DOWN` times weaker than the former, and at least
  :data:`BRACKET_MARGIN` of the bracket's width from its ends. The walk stops after
  ``values`` strengths or when the bracket is narrower than :data:`BRACKET_MARGIN` of its top.
  If the test value is missed, the bound is tried instead (the walk then ends there). Each
  replicate's crossing (where LB turns positive) is interpolated between the bracket's ends,
  linearly in the squared strength for the gap (it grows as its square) and, for the signature
  test, each candidate's z linearly in the strength (z grows as the shift, on the replicate's
  own noise: :func:`_z_crossing`), the weaker of the two crossings; the limit is the
  ceil(power x replicates)-th smallest crossing. Empty (NaN) when the bound is detected with
  less power. A limit interpolated from one rung far above it is
  the interpolation's, not the data's: margins saturate (z grows ever slower as the
  bootstrap's spread grows with the shift) and some effects grow as the strength's square
  (``nonlinearity``), so the walk evaluates a rung where the limit is expected and
  interpolates over the last bracket only (docs/validation.md, Diagnose: detection limits).
* **The limit's interval.** The limit estimates the power-quantile of the crossings' distribution;
  its 95 % interval is the distribution-free one of that quantile, [X_(r), X_(s)] of the
  sorted crossings with ranks from Binomial(replicates, power)
  (:func:`waveforest.stats.proportion.quantile_ranks`; 20 replicates at 0.8: the 12th and the
  20th). A replicate that misses the value above the limit crosses between the stronger
  values evaluated, so the upper end can lie beyond it; NaN when some replicate misses the
  strongest value tried. A lower end at the bracket's weaker value is at most that value
  (weaker ones are not evaluated). Like the Wilson intervals, it assumes independent replicates.

**The floor calibrated on twins.** The off replicates are data without effect on this very
design: the gap they give is the noise floor by definition. Their mean gap over their mean
bootstrap floor is the factor ``floor_scale`` (:func:`floor_calibration`) by which the
diagnosis multiplies every noise floor (:meth:`.gap.GapData.build`), the real data's and the
replicates' alike: every test below and the diagnosis's verdict compare a gap's interval with
the calibrated floor. With fewer than :data:`MIN_CALIBRATION_REPLICATES` replicates the factor
stays 1.

The off value is evaluated in every replicate too: its power is the false-alarm rate of the
test on this design (in-sample: the factor comes from the same replicates). A limit is never outside the values tried: "not reached" (NaN) when the
strongest is detected with less power. Cost: ``pool`` x (1 + values evaluated) simulations of
all pulses (one more set with ``pulses_per_value`` > 1), whatever ``replicates``. The
candidates' walks run side by side, and each step simulates its values seed by seed: a seed's
plants (the study's scene cache holds about one seed's) serve every value of the step.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import ALL_FEATURES, GapData, cell_statistics, masked_summary, sample_universe
from waveforest.diagnose.replicate_cache import Simulator, effects_key, simulate_all
from waveforest.diagnose.search import SearchSettings
from waveforest.diagnose.signature_test import SignatureTest, pooled_terms, terms
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.rng import named_generator, named_seeds
from waveforest.stats.bootstrap import bootstrap_weights, cluster_df
from waveforest.stats.proportion import limit_interval, quantile_ranks, strongest_tried, wilson_interval

MIN_CALIBRATION_REPLICATES = 5
"""Fewest off replicates from which the noise floor is calibrated (:func:`floor_calibration`)."""


@dataclass(frozen=True)
class FloorCalibration:
    """The noise floor calibrated on pseudo-real data without effect (module docstring).

    Attributes
    ----------
    scale : float
        Factor on the bootstrap floor: ``gap / floor`` (1 when not calibrated).
    gap, floor : float
        Mean total gap and mean bootstrap noise floor over the off replicates, squared pooled SDs.
    replicates : int
        Off replicates (0: none run).
    """

    scale: float = 1.0
    gap: float = math.nan
    floor: float = math.nan
    replicates: int = 0


def floor_calibration(off: np.ndarray) -> FloorCalibration:
    """:class:`FloorCalibration` of off replicates ``off`` ((R, 3): gap, bootstrap floor and
    lower bound of the excess, as :class:`_Replicate` tests them); scale 1 with fewer than
    :data:`MIN_CALIBRATION_REPLICATES` finite rows."""
    off = np.asarray(off, dtype=np.float64).reshape(-1, 3)
    ok = off[np.isfinite(off[:, :2]).all(axis=1) & (off[:, 1] > 0)]
    gap, floor = (float(ok[:, 0].mean()), float(ok[:, 1].mean())) if len(ok) else (math.nan, math.nan)
    scale = gap / floor if len(ok) >= MIN_CALIBRATION_REPLICATES and gap > 0 else 1.0
    return FloorCalibration(scale=float(scale), gap=gap, floor=floor, replicates=len(ok))


def _calibrated(res: np.ndarray, scale: float) -> np.ndarray:
    """Replicate results (gap, floor, excess lower bound) with the floor times ``scale``."""
    res = np.array(res, dtype=np.float64, copy=True)
    res[:, 2] -= (scale - 1.0) * res[:, 1]
    res[:, 1] *= scale
    return res


LIMIT_COLUMNS = ("effect", "unit", "smallest_detectable", "limit_ci_low", "limit_ci_high", "status", "upper_bound",
                 "test_value", "sees_test_value", "power", "replicates", "power_at_bound", "power_at_bound_ci_low",
                 "power_at_bound_ci_high", "power_at_test", "power_at_test_ci_low", "power_at_test_ci_high")
"""Columns of ``detection_limits.csv`` (:func:`detection_limits`), a contract with the report:
effect and unit; ``smallest_detectable`` the limit (NaN unless ``status`` is "detected");
``limit_ci_low`` <= ``limit_ci_high`` its 95 % interval (module docstring), NaN on the side of
the strongest value tried when it lies beyond it (both NaN without a limit);
``status`` "detected" or "not reached" (the far bound ``upper_bound``, tried when the test value
is missed, is detected in fewer than ``power`` x ``replicates`` replicates: "not reached up to
upper_bound");
``test_value`` the effect's realistic size (:data:`waveforest.effects.CATALOGUE`) and
``sees_test_value`` whether the limit lies at or below it (the data can see an effect of that size);
``power`` the power required and ``replicates`` the pseudo-real replicates per value;
``power_at_bound`` the share of replicates that detect ``upper_bound``, with its Wilson interval,
NaN where the bound was not tried (the test value was detected with power);
``power_at_test`` the same at the test value (always the walk's first value)."""

CURVE_COLUMNS = ("effect", "value", "strength", "replicates", "detected", "power", "power_ci_low", "power_ci_high",
                 "gap", "noise_floor", "excess_ci_low", "signature_margin")
"""Columns of ``detection_curve.csv``: one row per candidate and value evaluated (off included):
``detected`` of ``replicates`` pseudo-real replicates detected it, ``power`` their share with its
95 % Wilson interval; gap, noise floor, the excess gap's lower bound and the signature test's margin
(:mod:`.signature_test`, > 0: it fires): medians over the replicates."""


@dataclass(frozen=True)
class PowerSettings:
    """Settings of the power analysis (config section ``diagnose.power``; defaults are the schema's).

    Attributes
    ----------
    replicates : int
        Independent pseudo-real data sets.
    values : int
        Strengths evaluated per candidate (off not counted): the test value, then steps towards
        the limit (module docstring); the bound replaces them when the test value is missed.
    power : float
        Share of replicates that must detect a value for it to count as detectable.
    pool : int
        Simulations of all pulses per model from which the replicates are drawn sample by
        sample (module docstring; at most ``replicates + 1`` are used).
    """

    replicates: int = 20
    values: int = 2
    power: float = 0.8
    pool: int = 2

    def __post_init__(self) -> None:
        if self.replicates < 1 or self.values < 1 or not 0.0 < self.power <= 1.0 or self.pool < 2:
            raise WaveforestError("diagnose.power: need replicates >= 1, values >= 1, 0 < power <= 1, pool >= 2")

    @property
    def needed(self) -> int:
        """Replicates that must detect a value: ceil(power x replicates)."""
        return max(1, math.ceil(self.power * self.replicates - 1e-9))


STEP_DOWN = 32.0
"""A next strength is at least the weakest detected one over this (the estimate from a rung far
above the limit can be low by more than ten times when margins saturate)."""

BRACKET_MARGIN = 0.1
"""A next strength stays this share of the bracket's width inside it; a bracket narrower than
this share of its top ends the walk."""


def _far_bound(name: str) -> float:
    """u of the bound on the test value's side of off."""
    return 1.0 if cat.to_u(name, CATALOGUE[name].test_value) >= cat.off_u(name) else 0.0


def _crossing(s_lo: float, lb_lo: float, s_hi: float, lb_hi: float) -> float:
    """Strength at which the excess gap's lower bound turns positive between two strengths,
    linear in strength squared (a shift of d pooled SDs adds d^2 to the gap, d ~ strength)."""
    if lb_lo > 0:
        return s_lo
    if lb_hi <= 0:
        return math.nan
    return math.sqrt(s_lo**2 + (s_hi**2 - s_lo**2) * (-lb_lo) / (lb_hi - lb_lo))


def _z_crossing(s_lo: float, w_lo: np.ndarray, s_hi: float, w_hi: np.ndarray) -> float:
    """Strength at which the signature test fires between two strengths, each candidate's z
    linear in strength (the effect adds to the replicate's own noise: its bootstrap and
    simulation side are the same at both); ``w`` = z / (c crit) per candidate, the test fires
    where some |w| first exceeds 1. Interpolating the margin (max |w| - 1) instead would let a
    replicate whose noise points against the effect cross too early: its |z| first falls."""
    w_lo, w_hi = np.nan_to_num(w_lo), np.nan_to_num(w_hi)
    if np.abs(w_lo).max(initial=0.0) > 1.0:
        return s_lo
    if np.abs(w_hi).max(initial=0.0) <= 1.0:
        return math.nan
    b = w_hi - w_lo
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.concatenate([(1.0 - w_lo) / b, (-1.0 - w_lo) / b])
    return s_lo + (s_hi - s_lo) * float(t[np.isfinite(t) & (t >= 0.0) & (t <= 1.0)].min())


def _crossings(strengths: np.ndarray, lbs: list, j: int, crossing=_crossing, values: list | None = None) -> np.ndarray:
    """Each replicate's crossing (``crossing``, default :func:`_crossing`, of ``values``, default
    ``lbs``) between rungs ``j - 1`` and ``j``; a replicate that does not detect rung ``j`` crosses
    between the first stronger rung it detects and the rung below that one, inf when it detects
    none.

    Parameters
    ----------
    strengths : (n_rungs,) float64
        Distance from off of each rung, increasing (rung 0 is off).
    lbs : list of (R,) float64 or None
        The replicates' scores per rung, > 0 where detected (excess lower bounds, or signature
        margins); None for a rung not evaluated (only rungs below ``j - 1`` may be).
    j : int
        The rung of the first interval, 1 <= j < n_rungs.

    Returns
    -------
    (R,) float64
        Strengths; the first interval's as in the limit (a replicate that detects rung j - 1
        crosses at it), inf beyond the strongest rung.
    """
    values = lbs if values is None else values
    out = np.full(len(lbs[j]), np.inf)
    todo = np.ones(len(out), dtype=bool)
    for i in range(j, len(strengths)):
        for r in np.flatnonzero(todo & (lbs[i] > 0)):
            out[r] = crossing(strengths[i - 1], values[i - 1][r], strengths[i], values[i][r])
        todo &= ~(lbs[i] > 0)
    return out


class _Pool:
    """The pool of simulations of all pulses: ``size`` seeds, each model simulated once per seed
    (lazily); the base model's simulation side with ``twins`` twins per pulse, the pseudo-real
    data with one (the same table when ``twins`` is 1)."""

    def __init__(self, keys, simulate, seeds, twins: int, progress):
        self.keys, self.simulate, self.seeds, self.twins, self.progress = keys, simulate, seeds, int(twins), progress
        self.cache: dict = {}

    def get(self, effects: dict, k: int, twins: int = 1) -> pd.DataFrame:
        key = (effects_key(effects), int(k), int(twins))
        if key not in self.cache:
            self.cache[key] = simulate_all(self.simulate, self.keys, effects, int(self.seeds[k]), int(twins))
            if self.progress is not None:
                self.progress(f"power: {effects} seed {k}")
        return self.cache[key]


def _assemble(tables: list[pd.DataFrame], pick: np.ndarray, universe: pd.Series) -> pd.DataFrame:
    """Rows of each field sample j from pool member ``pick[j]``: one data set drawn sample by sample."""
    parts = []
    for k, t in enumerate(tables):
        j = universe.index.get_indexer(t["sample_id"].astype(str))
        parts.append(t[(j >= 0) & (pick[np.maximum(j, 0)] == k)])
    return pd.concat(parts, ignore_index=True)


class _Replicate:
    """One pseudo-real replicate: per field sample the pool member of its pseudo-real data and
    another of its simulation side, and its bootstrap weights."""

    def __init__(self, pool: _Pool, settings: SearchSettings, seed: int, universe):
        s_pick, _, s_boot = named_seeds("power_replicate", int(seed), n=3)
        n_pool = len(pool.seeds)
        rng = named_generator("power_replicate", int(s_pick))
        self.real_pick = rng.integers(0, n_pool, len(universe))
        self.sim_pick = (self.real_pick + rng.integers(1, n_pool, len(universe))) % n_pool  # another member
        self.pool, self.settings, self.universe = pool, settings, universe
        self.sim = _assemble([pool.get({}, k, settings.replicates) for k in range(n_pool)], self.sim_pick, universe)
        self.weights = bootstrap_weights(universe, settings.n_boot, s_boot)

    def test(self, effects: dict) -> tuple[tuple[float, float, float], tuple[pd.Series, np.ndarray]]:
        """Pseudo-real data under ``effects`` against the simulation side: (gap, noise floor, lower
        bound of the excess gap's interval) over the search's features (as :func:`.gap.gap_report`
        gives them), and the signature test's terms (:func:`.signature_test.terms`), from one
        reduction to per-sample sums."""
        s = self.settings
        real = _assemble([self.pool.get(effects, k) for k in range(len(self.pool.seeds))], self.real_pick,
                         self.universe)
        extra = tuple(f for f in ALL_FEATURES if f not in s.features and f in real.columns and f in self.sim.columns)
        data = GapData.build(real, self.sim, self.universe, features=tuple(s.features) + extra, floors=s.floors,
                             min_pulses=s.min_pulses, min_samples=s.min_samples)
        point, boot = cell_statistics(data), cell_statistics(data, self.weights)
        mask = data.valid & np.isin(np.asarray(data.features), s.features)[None, :]
        if not mask.any():
            raise WaveforestError("gap: no cell has enough real and simulated pulses to compare")
        gap, low, _, floor, _ = masked_summary(data, point, boot, mask, s.alpha)
        return (float(gap), float(floor), float(low - floor)), pooled_terms(data, point, boot)


def _null_replicates(keys: pd.DataFrame, simulate: Simulator, settings: SearchSettings, power: PowerSettings,
                     seed: int, progress) -> tuple[_Pool, list[_Replicate], list]:
    """The pool, the replicates and their tests without effect (:meth:`_Replicate.test`, under the
    bootstrap floor)."""
    keys = keys.assign(sample_id=keys["sample_id"].astype(str))
    settings = replace(settings, floor_scale=1.0)  # the bootstrap floor; calibrated by the caller
    universe = sample_universe(keys)
    n_pool = min(power.pool, power.replicates + 1)
    pool = _Pool(keys, simulate, named_seeds("power", int(seed), n=n_pool), settings.replicates, progress)
    reps = [_Replicate(pool, settings, s, universe)
            for s in named_seeds("power", int(seed), 1, n=power.replicates)]
    return pool, reps, [r.test({}) for r in reps]


def calibrate_floor(keys: pd.DataFrame, simulate: Simulator, settings: SearchSettings, power: PowerSettings,
                    seed: int, *, progress: Callable[[str], None] | None = None) -> FloorCalibration:
    """The noise floor's calibration alone: :func:`detection_limits`' off replicates (same
    seeds, same pool: the factor the diagnosis applies), without the walks."""
    if keys.empty:
        raise WaveforestError("diagnose: no pulse for the power analysis")
    return floor_calibration(np.array([gap for gap, _ in _null_replicates(keys, simulate, settings, power, seed,
                                                                          progress)[2]]))


def _detected(res: np.ndarray) -> np.ndarray:
    """Replicates (rows of gap, floor, excess lower bound, signature margin) that detect their
    effect: the excess gap's lower bound above 0, or the signature test fires."""
    return (res[:, 2] > 0) | (res[:, 3] > 0)


def _signature_test(pool: _Pool, reps: list[_Replicate], walks: dict, off_terms: list, alpha: float) -> SignatureTest:
    """The signature test of the candidates at their test values (the walks' first values: the
    pool's first seed against the base model's, common random numbers), calibrated on the
    replicates' terms without effect ``off_terms``. The test value, not the bound: the shape of
    an effect near its limit is that of a moderate effect, not of the strongest (saturated
    echoes, a crown's worth of clumping)."""
    s, universe = reps[0].settings, reps[0].universe
    kw = {"floors": s.floors, "min_pulses": s.min_pulses, "min_samples": s.min_samples}
    base = pool.get({}, 0)
    sigs = {name: terms(pool.get(w.effects(w.test), 0), base, universe, **kw)[0] for name, w in walks.items()}
    return SignatureTest.calibrate(sigs, off_terms, alpha, cluster_df(universe))


def _results(tests: list, scale: float, signature: SignatureTest | None) -> np.ndarray:
    """(R, 4 + m) rows of the replicates' ``tests`` (:meth:`_Replicate.test`): gap, floor and
    excess lower bound under the floor calibrated by ``scale``, the signature margin (-inf
    without a signature test), and each of its m candidates' z / (c crit) (none without)."""
    base = _calibrated([g for g, _ in tests], scale)
    if signature is None:
        return np.column_stack([base, np.full(len(tests), -math.inf)])
    zs = [signature.z(*t) for _, t in tests]
    margins = [signature.margin_of(z)[0] for z in zs]
    w = np.array([[z[e] / (signature.scale[e] * signature.crit) for e in signature.signatures] for z in zs])
    return np.column_stack([base, margins, w])


def _limit(strengths: np.ndarray, scores: list, needed: int) -> tuple[float, np.ndarray]:
    """The limit from results at increasing ``strengths`` (rung 0 off; ``scores`` their rows of
    :func:`_results`), interpolated below the weakest rung j from which every stronger one is
    detected with power: (limit, the replicates' sorted crossings); NaN and no crossings when
    the strongest rung is not detected with power."""
    det = [int(_detected(r).sum()) >= needed for r in scores]
    if not det[-1]:
        return math.nan, np.array([])
    j = max(1, min(i for i in range(len(det)) if all(det[i:])))
    cross = np.sort(np.minimum(  # the weaker of the two tests' crossings
        _crossings(strengths, [r[:, 2] for r in scores], j),
        _crossings(strengths, [r[:, 3] for r in scores], j, _z_crossing, [r[:, 4:] for r in scores])))
    return min(cross[needed - 1], strengths[j]), cross  # within the range tried


@dataclass
class _Walk:
    """One candidate's walk towards its limit (module docstring): ``rows`` the results
    (:func:`_results`) of each strength evaluated, ``next`` the strength to evaluate (None: the
    walk is done)."""

    name: str
    values: int
    test: float
    bound: float
    rows: dict = field(default_factory=dict)
    next: float | None = None

    @classmethod
    def start(cls, name: str, values: int) -> _Walk:
        """The walk of ``name``, at its test value."""
        u0 = cat.off_u(name)
        test = abs(cat.to_u(name, CATALOGUE[name].test_value) - u0)
        return cls(name, values, test, abs(_far_bound(name) - u0), next=test)

    def u(self, strength: float) -> float:
        """The search coordinate at ``strength`` (distance from off, on the test value's side)."""
        u0 = cat.off_u(self.name)
        return u0 + math.copysign(strength, _far_bound(self.name) - u0)

    def value(self, strength: float) -> float:
        """The effect's value at ``strength``."""
        return cat.from_u(self.name, self.u(strength))

    def effects(self, strength: float) -> dict:
        """The model with the effect at ``strength``."""
        return cat.with_effect({}, self.name, self.value(strength))

    def rungs(self, off: np.ndarray) -> tuple[np.ndarray, list]:
        """(strengths, results) of off and every strength evaluated, weakest first."""
        ks = sorted(self.rows)
        return np.array([0.0, *ks]), [off, *(self.rows[k] for k in ks)]

    def record(self, res: np.ndarray, off: np.ndarray, needed: int) -> None:
        """The results (:func:`_results`) at ``next``, and the strength to try after it."""
        self.rows[self.next] = res
        seen = {k: int(_detected(r).sum()) >= needed for k, r in self.rows.items()}
        self.next = None
        if not seen[self.test]:  # the test value missed: the bound decides
            if self.bound not in self.rows:
                self.next = self.bound
            return
        hi = min(k for k, ok in seen.items() if ok)
        lo = max([0.0, *(k for k, ok in seen.items() if not ok and k < hi)])
        width = hi - lo
        if len(self.rows) >= self.values or width < BRACKET_MARGIN * hi:
            return
        estimate = _limit(*self.rungs(off), needed)[0]
        low = hi / STEP_DOWN if lo == 0.0 else lo + BRACKET_MARGIN * width
        self.next = float(np.clip(estimate, low, hi - BRACKET_MARGIN * width)) if math.isfinite(estimate) else None


def detection_limits(keys: pd.DataFrame, simulate: Simulator, settings: SearchSettings, power: PowerSettings,
                     seed: int, *, progress: Callable[[str], None] | None = None, tables: dict | None = None,
                     calibration: dict | None = None) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The power analysis of the module docstring for every candidate of ``settings``.

    Parameters
    ----------
    keys : DataFrame
        The diagnosed pulses (as for :func:`.search.search`).
    simulate : Simulator
        The diagnosis's simulator (base model included).
    settings : SearchSettings
        Candidates, bootstrap, alpha, gap settings and ``replicates`` (twins per pulse of the
        simulation side).
    power : PowerSettings
    seed : int
        Master seed of the replicates.
    progress : callable, optional
        Called with a label after each simulation.
    tables : dict, optional
        Filled with the pseudo-real feature tables of the pool's first seed, keyed by
        :func:`.replicate_cache.effects_key` (off included): one seed for all, so any two are
        common-random-number pairs (:func:`.missing_effects.signatures` reads them).
    calibration : dict, optional
        Filled with ``{"floor": FloorCalibration, "signature": SignatureTest or None}`` of the
        off replicates; the tests of the walks use that calibrated floor (``settings.floor_scale``
        is ignored) and that signature test (None with ``settings.signature_alpha`` None).

    Returns
    -------
    limits : DataFrame
        :data:`LIMIT_COLUMNS`, one row per candidate; ``smallest_detectable`` NaN when neither
        the test value nor the far bound (``upper_bound``) is detected in
        :attr:`PowerSettings.needed` replicates.
    curve : DataFrame
        :data:`CURVE_COLUMNS`, per candidate its off value and the values evaluated, weakest
        first (``strength``: distance from off in the search coordinate; gap, floor and lower
        bound: medians over the replicates).
    """
    if keys.empty:
        raise WaveforestError("diagnose: no pulse for the power analysis")
    if not settings.candidates:
        return pd.DataFrame(columns=list(LIMIT_COLUMNS)), pd.DataFrame(columns=list(CURVE_COLUMNS))
    pool, reps, off_tests = _null_replicates(keys, simulate, settings, power, seed, progress)
    cal = floor_calibration(np.array([g for g, _ in off_tests]))
    walks = {name: _Walk.start(name, power.values) for name in settings.candidates}
    sig_test, off = None, None
    while active := [w for w in walks.values() if w.next is not None]:
        tried = [w.effects(w.next) for w in active]
        for k in range(len(pool.seeds)):  # seed by seed: each seed's base plants stay in the scene cache
            for effects in tried:
                pool.get(effects, k)
        if off is None:  # the first step simulated every test value: the signatures
            if settings.signature_alpha is not None:
                sig_test = _signature_test(pool, reps, walks, [t for _, t in off_tests], settings.signature_alpha)
            off = _results(off_tests, cal.scale, sig_test)
        for w, effects in zip(active, tried):
            w.record(_results([r.test(effects) for r in reps], cal.scale, sig_test), off, power.needed)
    if calibration is not None:
        calibration.update(floor=cal, signature=sig_test)
    limits, curve = [], []
    for name in settings.candidates:
        w = walks[name]
        strengths, scores = w.rungs(off)
        s, cross = _limit(strengths, scores, power.needed)
        limit = ci_low = ci_high = math.nan
        if math.isfinite(s):
            limit = w.value(s)
            r_lo, r_hi = (quantile_ranks(power.replicates, power.power) if power.power < 1
                          else (power.replicates, power.replicates + 1))
            # rank 0 is off (strength 0: inf on an inverse scale), rank R + 1 or an inf crossing NaN
            ends = np.concatenate([[0.0], cross, [np.inf]])[[r_lo, r_hi]]
            weak, strong = (cat.value_interval(name, w.u(e), w.u(e))[0] if np.isfinite(e) else math.nan for e in ends)
            # in the values' order (clumping and nonlinearity fall as the effect grows), the
            # unbounded strong end NaN
            rising = cat.value_interval(name, cat.off_u(name), cat.off_u(name))[0] < w.value(w.bound)
            ci_low, ci_high = (weak, strong) if rising else (strong, weak)
        at = {}
        for key, strength in (("bound", w.bound), ("test", w.test)):
            p = float(_detected(w.rows[strength]).mean()) if strength in w.rows else math.nan
            at[key] = (p, *wilson_interval(p, power.replicates))
        limits.append({"effect": name, "unit": cat.UNITS[name], "smallest_detectable": limit,
                       "limit_ci_low": ci_low, "limit_ci_high": ci_high,
                       "status": "detected" if np.isfinite(limit) else "not reached",
                       "upper_bound": w.value(w.bound), "test_value": float(CATALOGUE[name].test_value),
                       "sees_test_value": bool(np.isfinite(limit) and s <= w.test + 1e-9),
                       "power": power.power, "replicates": power.replicates,
                       "power_at_bound": at["bound"][0], "power_at_bound_ci_low": at["bound"][1],
                       "power_at_bound_ci_high": at["bound"][2], "power_at_test": at["test"][0],
                       "power_at_test_ci_low": at["test"][1], "power_at_test_ci_high": at["test"][2]})
        for strength, res in zip(strengths, scores):
            hits = int(_detected(res).sum())
            p_lo, p_hi = wilson_interval(hits / power.replicates, power.replicates)
            curve.append({"effect": name, "value": w.value(strength), "strength": float(strength),
                          "replicates": power.replicates, "detected": hits, "power": hits / power.replicates,
                          "power_ci_low": p_lo, "power_ci_high": p_hi,
                          "gap": float(np.median(res[:, 0])), "noise_floor": float(np.median(res[:, 1])),
                          "excess_ci_low": float(np.median(res[:, 2])),
                          "signature_margin": float(np.median(res[:, 3])) if np.isfinite(res[:, 3]).any() else math.nan})
    if tables is not None:  # one seed for all models: common-random-number pairs
        tables.update({eff: t for (eff, k, twins), t in pool.cache.items() if k == 0 and twins == 1})
    return pd.DataFrame(limits, columns=list(LIMIT_COLUMNS)), pd.DataFrame(curve, columns=list(CURVE_COLUMNS))


def interval_of(r) -> str:
    """:func:`limit_interval` of a row of :data:`LIMIT_COLUMNS` ("" for tables without it)."""
    strongest = strongest_tried(float(r.upper_bound), float(getattr(r, "test_value", math.nan)),
                                float(getattr(r, "power_at_bound", 0.0)))
    return limit_interval(float(getattr(r, "limit_ci_low", math.nan)), float(getattr(r, "limit_ci_high", math.nan)),
                          strongest)


def power_at_test(r) -> str:
    """``0.75 [0.53, 0.89]``: the power measured at the test value with its Wilson interval, of a
    row of :data:`LIMIT_COLUMNS`; "" where it was not evaluated (or a table without it)."""
    p = float(getattr(r, "power_at_test", math.nan))
    return f"{p:.2f} [{r.power_at_test_ci_low:.2f}, {r.power_at_test_ci_high:.2f}]" if math.isfinite(p) else ""


def seen_at_test(limits: pd.DataFrame) -> pd.Series:
    """Per row of :data:`LIMIT_COLUMNS`, whether the data see the candidate at its test value:
    "yes" (``sees_test_value``: the limit lies at or below it), "edge" (it does not, but the
    Wilson interval of the power measured there reaches ``power``: the replicates' draw may
    have missed it) or "no" (that interval lies wholly below ``power``, or no power was
    measured there). Tables without ``sees_test_value`` read "yes" where a limit was found."""
    sees = (limits["sees_test_value"].astype(bool) if "sees_test_value" in limits
            else limits["smallest_detectable"].notna())
    high, need = (np.asarray(limits.get(c, np.nan), np.float64) for c in ("power_at_test_ci_high", "power"))
    reach = high >= need - 1e-9  # a missing column is NaN: never reaches
    return pd.Series(np.where(sees, "yes", np.where(reach, "edge", "no")), index=limits.index)


def verdict_with_limits(verdict: str, limits: pd.DataFrame, lead: str = "") -> str:
    """The verdict with the detection limits, e.g. ``none: seen in >= 80 % of the model's twins
    from understory 0.8 LAI, xy_error 0.15 m`` or ``inconclusive: these data cannot see
    nonlinearity at 150 DN (not reached up to 50 DN); seen in >= 80 % of the model's twins from
    understory 0.8 LAI``.

    A limit is a power (``limits.power``) on pseudo-real data, the model's own twins: no promise
    that a larger effect is absent from data that differ from the model in other ways, so the
    text never says "no effect larger than". A limit not reached reads "not reached up to" the
    strongest value tried. Candidates :func:`seen_at_test` puts at the "edge" read "at the edge
    of what these data see", with the power measured at the test value. ``lead`` (what was
    named, or why none was) comes first; the limits of an effect with values on both sides of
    off (lad_shift, leaf_albedo) are said to lie on its test value's side only (the walk runs
    from off towards it).
    """
    if limits.empty:
        return f"{verdict}: {lead}" if lead else verdict
    seen = seen_at_test(limits)
    found = limits[limits["smallest_detectable"].notna() & (seen == "yes")]

    def limit_of(r) -> str:
        there = f"power {p} there, " if (p := power_at_test(r)) else ""
        if pd.isna(r.smallest_detectable):
            return f"{there}not reached up to {r.upper_bound:.3g} {r.unit}"
        return f"{there}limit {r.smallest_detectable:.3g} {interval_of(r)} {r.unit}".replace("  ", " ")

    parts = [lead] if lead else []
    two_sided = [e for e in limits["effect"] if cat.effect(e).bounds[0] < cat.effect(e).off < cat.effect(e).bounds[1]]
    for label, words in (("no", "these data cannot see "), ("edge", "at the edge of what these data see: ")):
        if len(rows := limits[seen == label]):
            parts.append(words + ", ".join(
                f"{r.effect} at {r.test_value:.3g} {r.unit} ({limit_of(r)})" if "test_value" in limits
                else f"{r.effect} ({limit_of(r)})" for r in rows.itertuples()))
    if len(found):
        values = ", ".join(f"{r.effect} {r.smallest_detectable:.3g} {r.unit}" for r in found.itertuples())
        power = float(limits["power"].iloc[0]) if "power" in limits else 0.8
        parts.append(f"seen in >= {power:.0%} of the model's twins from {values}")
    if two_sided and len(parts) > bool(lead):
        parts.append(f"limits of {', '.join(two_sided)} on the test value's side of off only")
    return f"{verdict}: " + "; ".join(parts) if parts else verdict
