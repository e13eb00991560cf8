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
  ``signature_alpha``; the candidates' signatures are those of their far bounds, the pool's
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
* **Ladder.** Per candidate, ``values`` strengths from its off value towards the bound on
  the side of its test value (search coordinate u, :mod:`.catalogue`): the bound, the test
  value itself, then halvings of the test value's distance from off (1/2, 1/4, ... of it).
  With the test value a rung, whether the data see it is a power measured there, not an
  interpolation (a saturating signature, as the understory's, bends the gap away from the
  square law the interpolation assumes). The ladder is walked from the bound down and stops
  at the first value whose power is below ``power`` (smaller ones are not evaluated). Each
  replicate's crossing (where LB turns positive) is interpolated between that value and the
  next stronger one (the off value below the weakest), linearly in the squared distance from
  off for the gap (it grows as its square) and linearly in the distance for the signature
  test's margin (z grows as the shift), the weaker of the two crossings; the limit is the
  ceil(power x replicates)-th smallest crossing. Empty (NaN) when the bound itself is detected
  with less power.
* **The limit's interval.** The limit estimates the power-quantile of the crossings' distribution;
  its 95 % interval is the distribution-free one of that quantile, [X_(r), X_(s)] of the
  sorted crossings with ranks from Binomial(replicates, power)
  (:func:`waveforest.stats.proportion.quantile_ranks`; 20 replicates at 0.8: the 12th and the
  20th). A replicate that misses the value above the limit crosses between the stronger
  values evaluated, so the upper end can lie beyond it; NaN when some replicate misses the
  bound itself. A lower end on the weaker ladder value is at most that value (weaker ones
  are not evaluated). Like the Wilson intervals, it assumes independent replicates.

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
from waveforest.stats.proportion import limit_interval, quantile_ranks, wilson_interval

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
the strongest value tried (``upper_bound``) when it lies beyond it (both NaN without a limit);
``status`` "detected" or "not reached" (the strongest value tried, ``upper_bound``, is detected
in fewer than ``power`` x ``replicates`` replicates: "not reached up to upper_bound");
``test_value`` the effect's realistic size (:data:`waveforest.effects.CATALOGUE`) and
``sees_test_value`` whether the limit lies at or below it (the data can see an effect of that size);
``power`` the power required and ``replicates`` the pseudo-real replicates per value;
``power_at_bound`` the share of replicates that detect ``upper_bound``, with its Wilson interval;
``power_at_test`` the same at the test value (a rung of the ladder: :func:`ladder`), NaN where
it was not evaluated (the walk stopped at the bound, or a ladder of one value)."""

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
        Ladder values per candidate (off not counted).
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


def ladder(name: str, n_values: int) -> np.ndarray:
    """Search coordinates of the ladder of ``name``, weakest first (module docstring).

    Returns
    -------
    (n_values,) float64
        u of the values at 1/2^(n-2), ..., 1/2, 1 of the test value's distance from off, then
        the far bound on the test value's side (``n_values`` 1: the bound alone).
    """
    u0, u_test = cat.off_u(name), cat.to_u(name, CATALOGUE[name].test_value)
    end = 1.0 if u_test >= u0 else 0.0
    frac = 2.0 ** -np.arange(n_values - 2, -1, -1, dtype=np.float64)
    return np.append(u0 + (u_test - u0) * frac, end)


def _crossing(s_lo: float, lb_lo: float, s_hi: float, lb_hi: float) -> float:
    """Strength at which the excess gap's lower bound turns positive between two strengths,
    linear in strength squared (a shift of d pooled SDs adds d^2 to the gap, d ~ strength)."""
    if lb_lo > 0:
        return s_lo
    if lb_hi <= 0:
        return math.nan
    return math.sqrt(s_lo**2 + (s_hi**2 - s_lo**2) * (-lb_lo) / (lb_hi - lb_lo))


def _linear_crossing(s_lo: float, m_lo: float, s_hi: float, m_hi: float) -> float:
    """Strength at which the signature test's margin turns positive between two strengths,
    linear in strength (z grows as the effect's shift)."""
    if m_lo > 0:
        return s_lo
    if m_hi <= 0:
        return math.nan
    return s_lo + (s_hi - s_lo) * (-m_lo) / (m_hi - m_lo)


def _crossings(strengths: np.ndarray, lbs: list, j: int, crossing=_crossing) -> np.ndarray:
    """Each replicate's crossing (``crossing``, default :func:`_crossing`) between rungs ``j - 1``
    and ``j``; a replicate that does not detect rung ``j`` crosses between the first stronger rung
    it detects and the rung below that one, inf when it detects none.

    Parameters
    ----------
    strengths : (n_rungs,) float64
        Distance from off of each rung, increasing (rung 0 is off).
    lbs : list of (R,) float64 or None
        The replicates' scores per rung, > 0 where detected (excess lower bounds, or signature
        margins with :func:`_linear_crossing`); None for a rung not evaluated (only rungs below
        ``j - 1`` may be).
    j : int
        The rung of the first interval, 1 <= j < n_rungs.

    Returns
    -------
    (R,) float64
        Strengths; the first interval's as in the limit (a replicate that detects rung j - 1
        crosses at it), inf beyond the strongest rung.
    """
    out = np.full(len(lbs[j]), np.inf)
    todo = np.ones(len(out), dtype=bool)
    for i in range(j, len(strengths)):
        for r in np.flatnonzero(todo & (lbs[i] > 0)):
            out[r] = crossing(strengths[i - 1], lbs[i - 1][r], strengths[i], lbs[i][r])
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
    seeds, same pool: the factor the diagnosis applies), without the ladders."""
    if keys.empty:
        raise WaveforestError("diagnose: no pulse for the power analysis")
    return floor_calibration(np.array([gap for gap, _ in _null_replicates(keys, simulate, settings, power, seed,
                                                                          progress)[2]]))


def _detected(res: np.ndarray) -> np.ndarray:
    """Replicates (rows of gap, floor, excess lower bound, signature margin) that detect their
    effect: the excess gap's lower bound above 0, or the signature test fires."""
    return (res[:, 2] > 0) | (res[:, 3] > 0)


def _signature_test(pool: _Pool, reps: list[_Replicate], walks: dict, off_terms: list, alpha: float) -> SignatureTest:
    """The signature test of the candidates at their far bounds (the walks' first values: the
    pool's first seed against the base model's, common random numbers), calibrated on the
    replicates' terms without effect ``off_terms``."""
    s, universe = reps[0].settings, reps[0].universe
    kw = {"floors": s.floors, "min_pulses": s.min_pulses, "min_samples": s.min_samples}
    base = pool.get({}, 0)
    sigs = {name: terms(pool.get(cat.with_effect({}, name, cat.from_u(name, w.us[-1])), 0), base, universe, **kw)[0]
            for name, w in walks.items()}
    return SignatureTest.calibrate(sigs, off_terms, alpha, cluster_df(universe))


def _results(tests: list, scale: float, signature: SignatureTest | None) -> np.ndarray:
    """(R, 4) rows of the replicates' ``tests`` (:meth:`_Replicate.test`): gap, floor and excess
    lower bound under the floor calibrated by ``scale``, and the signature margin (-inf without
    a signature test)."""
    margins = [-math.inf if signature is None else signature.margin(*t)[0] for _, t in tests]
    return np.column_stack([_calibrated([g for g, _ in tests], scale), margins])


@dataclass
class _LadderWalk:
    """One candidate's walk down its ladder ``us`` (search coordinate), from the far bound
    towards off, while a value is detected in at least ``needed`` replicates: ``k`` the value
    under test (at the end: the first not detected, -1 if all were), ``rows`` each tested value's
    results (:func:`_detected`)."""

    name: str
    us: np.ndarray
    k: int
    rows: dict = field(default_factory=dict)
    done: bool = False

    @classmethod
    def start(cls, name: str, values: int) -> _LadderWalk:
        """The walk of ``name`` over :func:`ladder` (``values`` values), at its far bound."""
        us = ladder(name, values)
        return cls(name, us, len(us) - 1)

    def record(self, res: np.ndarray, needed: int) -> None:
        """The results (R, 4) of value ``k`` (:func:`_detected`); the walk stops at a value not
        detected or at off."""
        self.rows[self.k] = res
        if _detected(res).sum() < needed:
            self.done = True
        else:
            self.k -= 1
            self.done = self.k < 0


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
        off replicates; the tests of the ladder use that calibrated floor (``settings.floor_scale``
        is ignored) and that signature test (None with ``settings.signature_alpha`` None).

    Returns
    -------
    limits : DataFrame
        :data:`LIMIT_COLUMNS`, one row per candidate; ``smallest_detectable`` NaN when the
        far bound (``upper_bound``) is detected in fewer than :attr:`PowerSettings.needed`
        replicates.
    curve : DataFrame
        :data:`CURVE_COLUMNS`, per candidate its off value and the ladder values evaluated,
        weakest first (``strength``: distance from off in the search coordinate; gap, floor
        and lower bound: medians over the replicates).
    """
    if keys.empty:
        raise WaveforestError("diagnose: no pulse for the power analysis")
    if not settings.candidates:
        return pd.DataFrame(columns=list(LIMIT_COLUMNS)), pd.DataFrame(columns=list(CURVE_COLUMNS))
    pool, reps, off_tests = _null_replicates(keys, simulate, settings, power, seed, progress)
    cal = floor_calibration(np.array([g for g, _ in off_tests]))
    walks = {name: _LadderWalk.start(name, power.values) for name in settings.candidates}
    sig_test, off = None, None
    while active := [w for w in walks.values() if not w.done]:
        tried = [cat.with_effect({}, w.name, cat.from_u(w.name, w.us[w.k])) for w in active]
        for k in range(len(pool.seeds)):  # seed by seed: each seed's base plants stay in the scene cache
            for effects in tried:
                pool.get(effects, k)
        if off is None:  # the first step simulated every far bound: the signatures
            if settings.signature_alpha is not None:
                sig_test = _signature_test(pool, reps, walks, [t for _, t in off_tests], settings.signature_alpha)
            off = _results(off_tests, cal.scale, sig_test)
        for w, effects in zip(active, tried):
            w.record(_results([r.test(effects) for r in reps], cal.scale, sig_test), power.needed)
    if calibration is not None:
        calibration.update(floor=cal, signature=sig_test)
    limits, curve = [], []
    for name in settings.candidates:
        w = walks[name]
        us, k, rows = w.us, w.k, w.rows
        u0 = cat.off_u(name)
        limit = ci_low = ci_high = math.nan
        if k < len(us) - 1:  # the far bound is detected: interpolate below the weakest detected value
            # rung 0 is off, rung i + 1 the ladder's value i; the weakest detected with power is rung k + 2
            strengths = np.abs(np.concatenate([[u0], us]) - u0)
            scores = [off] + [rows.get(i) for i in range(len(us))]
            cross = np.sort(np.minimum(  # the weaker of the two tests' crossings
                _crossings(strengths, [None if r is None else r[:, 2] for r in scores], k + 2),
                _crossings(strengths, [None if r is None else r[:, 3] for r in scores], k + 2, _linear_crossing)))
            # within the range tried: at most the weakest value detected with power
            s = min(cross[power.needed - 1], strengths[k + 2])
            limit = cat.from_u(name, u0 + math.copysign(s, us[-1] - u0))
            r_lo, r_hi = (quantile_ranks(power.replicates, power.power) if power.power < 1
                          else (power.replicates, power.replicates + 1))
            # rank 0 is off (strength 0: inf on an inverse scale), rank R + 1 or an inf crossing NaN
            ends = np.concatenate([[0.0], cross, [np.inf]])[[r_lo, r_hi]]
            weak, strong = (cat.value_interval(name, u, u)[0] if np.isfinite(e) else math.nan
                            for e, u in zip(ends, u0 + np.copysign(ends, us[-1] - u0)))
            # in the values' order (clumping and nonlinearity fall as the effect grows), the
            # unbounded strong end NaN
            rising = cat.value_interval(name, u0, u0)[0] < cat.from_u(name, us[-1])
            ci_low, ci_high = (weak, strong) if rising else (strong, weak)
        n_bound = int(_detected(rows[len(us) - 1]).sum())
        b_lo, b_hi = wilson_interval(n_bound / power.replicates, power.replicates)
        # the test value is the rung below the bound (values >= 2), evaluated unless the walk stopped at the bound
        p_test = float(_detected(rows[len(us) - 2]).mean()) if len(us) >= 2 and len(us) - 2 in rows else math.nan
        t_lo, t_hi = wilson_interval(p_test, power.replicates)
        test = float(CATALOGUE[name].test_value)
        sees = bool(np.isfinite(limit) and abs(cat.to_u(name, limit) - u0) <= abs(cat.to_u(name, test) - u0) + 1e-9)
        limits.append({"effect": name, "unit": cat.UNITS[name], "smallest_detectable": limit,
                       "limit_ci_low": ci_low, "limit_ci_high": ci_high,
                       "status": "detected" if np.isfinite(limit) else "not reached",
                       "upper_bound": cat.from_u(name, us[-1]), "test_value": test, "sees_test_value": sees,
                       "power": power.power, "replicates": power.replicates, "power_at_bound": n_bound / power.replicates,
                       "power_at_bound_ci_low": b_lo, "power_at_bound_ci_high": b_hi,
                       "power_at_test": p_test, "power_at_test_ci_low": t_lo, "power_at_test_ci_high": t_hi})
        for kk, res in sorted({-1: off, **rows}.items()):
            u = u0 if kk < 0 else us[kk]
            hits = int(_detected(res).sum())
            p_lo, p_hi = wilson_interval(hits / power.replicates, power.replicates)
            curve.append({"effect": name, "value": cat.from_u(name, u), "strength": abs(u - u0),
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
    return limit_interval(float(getattr(r, "limit_ci_low", math.nan)), float(getattr(r, "limit_ci_high", math.nan)),
                          float(r.upper_bound))


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
    off (lad_shift, leaf_albedo) are said to lie on its test value's side only (the ladder runs
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
