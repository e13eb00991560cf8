"""Detection limits: the smallest value of each candidate effect that this data would detect.

docs/method.md §(j) (detection limits). A power analysis on simulated effects, with the
design of the data and the test that decides the verdict ``none``:

* **Pseudo-real data.** The real pulses (``keys``: same pulses, samples and strata) are
  simulated with the candidate at a value v (one twin per pulse, as the real data have one
  record per pulse) and stand in for the measurement; the base model, simulated with another
  seed and ``pulses_per_value`` twins per pulse, is the simulation side.
* **The test.** :func:`.gap.gap_report` with the search's settings, the same cluster
  bootstrap over field samples and ``alpha``: v is *detected* in a replicate when the lower
  bound of the excess gap's interval is above 0 (the base model's gap is significant above
  its noise floor), the condition without which the search names nothing.
* **Replicates.** ``replicates`` independent pseudo-real data sets (seeds), each with its own
  simulation side and bootstrap weights; within one replicate every effect and value shares
  the seeds (common random numbers), so the excess gap's lower bound LB(v) varies with the
  effect only. Power(v) = share of replicates that detect v.
* **Ladder.** Per candidate, ``values`` strengths from its off value towards the bound on
  the side of its test value (search coordinate u, :mod:`.catalogue`), geometric: the
  distance from off is 1/2^(n-1), ..., 1/4, 1/2, 1 of the way to the bound. The ladder is
  walked from the bound down and stops at the first value whose power is below ``power``
  (smaller ones are not evaluated). Each replicate's crossing (where LB turns positive) is
  interpolated between that value and the next stronger one (the off value below the
  weakest), linearly in the squared distance from off (the gap grows as its square); the
  limit is the ceil(power x replicates)-th smallest crossing. Empty (NaN) when the bound
  itself is detected with less power.

The off value is evaluated in every replicate too: its power is the false-alarm rate of the
test on this design. Cost: ``replicates`` x (2 + values evaluated) simulations of all pulses.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import gap_report, sample_universe
from waveforest.diagnose.replicate_cache import Simulator, effects_key, simulate_all
from waveforest.diagnose.search import SearchSettings
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.rng import named_seeds
from waveforest.stats.bootstrap import bootstrap_weights

LIMIT_COLUMNS = ("effect", "unit", "smallest_detectable", "upper_bound", "power", "replicates")
"""Columns of ``detection_limits.csv`` (:func:`detection_limits`), a contract with the report."""

CURVE_COLUMNS = ("effect", "value", "strength", "replicates", "power", "gap", "noise_floor", "excess_ci_low")
"""Columns of ``detection_curve.csv``: one row per candidate and value evaluated (off included)."""


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
    """

    replicates: int = 1
    values: int = 2
    power: float = 0.8

    def __post_init__(self) -> None:
        if self.replicates < 1 or self.values < 1 or not 0.0 < self.power <= 1.0:
            raise WaveforestError("diagnose.power: need replicates >= 1, values >= 1, 0 < power <= 1")

    @property
    def needed(self) -> int:
        """Replicates that must detect a value: ceil(power x replicates)."""
        return max(1, math.ceil(self.power * self.replicates - 1e-9))


def ladder(name: str, n_values: int) -> np.ndarray:
    """Search coordinates of the ladder of ``name``, weakest first (module docstring).

    Returns
    -------
    (n_values,) float64
        u of the values at 1/2^(n-1), ..., 1/2, 1 of the way from off to the far bound on
        the test value's side.
    """
    u0 = cat.off_u(name)
    end = 1.0 if cat.to_u(name, CATALOGUE[name].test_value) >= u0 else 0.0
    frac = 2.0 ** -np.arange(n_values - 1, -1, -1, dtype=np.float64)
    return u0 + (end - u0) * frac


def _crossing(s_lo: float, lb_lo: float, s_hi: float, lb_hi: float) -> float:
    """Strength at which the excess gap's lower bound turns positive between two strengths,
    linear in strength squared (a shift of d pooled SDs adds d^2 to the gap, d ~ strength)."""
    if lb_lo > 0:
        return s_lo
    if lb_hi <= 0:
        return math.nan
    return math.sqrt(s_lo**2 + (s_hi**2 - s_lo**2) * (-lb_lo) / (lb_hi - lb_lo))


class _Replicate:
    """One pseudo-real replicate: its seeds, base simulation side and bootstrap weights."""

    def __init__(self, keys, simulate, settings: SearchSettings, seed, universe, progress):
        s_real, s_sim, s_boot = named_seeds("power_replicate", seed, n=3)
        self.keys, self.simulate, self.settings, self.progress = keys, simulate, settings, progress
        self.s_real, self.s_boot = int(s_real), s_boot
        self.sim = self._count(simulate_all(simulate, keys, {}, int(s_sim), settings.replicates), "power: base")
        self.universe = universe
        self.weights = bootstrap_weights(universe, settings.n_boot, s_boot)
        self.tables = None

    def _count(self, table, label):
        if self.progress is not None:
            self.progress(label)
        return table

    def test(self, effects: dict) -> tuple[float, float, float]:
        """(gap, noise floor, lower bound of the excess gap's interval) of pseudo-real data under
        ``effects``; the pseudo-real table goes to ``self.tables`` when that is a dict."""
        real = self._count(simulate_all(self.simulate, self.keys, effects, self.s_real, 1), f"power: {effects}")
        if self.tables is not None:
            self.tables[effects_key(effects)] = real
        s = self.settings
        rep = gap_report(real, self.sim, n_boot=s.n_boot, alpha=s.alpha, wasserstein=False, universe=self.universe,
                         weights=self.weights, **s.gap_kw)
        tot = rep.summary.loc["total"]
        return float(tot["gap"]), float(tot["noise_floor"]), float(tot["excess_ci_low"])


def detection_limits(keys: pd.DataFrame, simulate: Simulator, settings: SearchSettings, power: PowerSettings,
                     seed: int, *, progress: Callable[[str], None] | None = None, tables: dict | None = None
                     ) -> tuple[pd.DataFrame, pd.DataFrame]:
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
        Filled with the first replicate's pseudo-real feature tables, keyed by
        :func:`.replicate_cache.effects_key` (off included): one seed for all, so any two are
        common-random-number pairs (:func:`.missing_effects.signatures` reads them).

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
    keys = keys.assign(sample_id=keys["sample_id"].astype(str))
    universe = sample_universe(keys)
    seeds = named_seeds("power", int(seed), n=power.replicates)
    reps = [_Replicate(keys, simulate, settings, int(s), universe, progress) for s in seeds]
    reps[0].tables = tables
    off = np.array([r.test({}) for r in reps])  # (R, 3)
    limits, curve = [], []
    for name in settings.candidates:
        us = ladder(name, power.values)
        u0 = cat.off_u(name)
        lbs: dict[int, np.ndarray] = {}
        rows = {}
        k = len(us) - 1
        while k >= 0:
            res = np.array([r.test(cat.with_effect({}, name, cat.from_u(name, us[k]))) for r in reps])
            lbs[k], rows[k] = res[:, 2], res
            if (res[:, 2] > 0).sum() < power.needed:
                break
            k -= 1
        limit = math.nan
        if k < len(us) - 1:  # the far bound is detected: interpolate below the weakest detected value
            u_lo, lb_lo = (u0, off[:, 2]) if k < 0 else (us[k], lbs[k])
            cross = [_crossing(abs(u_lo - u0), a, abs(us[k + 1] - u0), b) for a, b in zip(lb_lo, lbs[k + 1])]
            s = np.sort(np.where(np.isnan(cross), np.inf, cross))[power.needed - 1]
            limit = cat.from_u(name, u0 + math.copysign(s, us[-1] - u0))
        limits.append({"effect": name, "unit": cat.UNITS[name], "smallest_detectable": limit,
                       "upper_bound": cat.from_u(name, us[-1]), "power": power.power,
                       "replicates": power.replicates})
        for kk, res in sorted({-1: off, **rows}.items()):
            u = u0 if kk < 0 else us[kk]
            curve.append({"effect": name, "value": cat.from_u(name, u), "strength": abs(u - u0),
                          "replicates": power.replicates, "power": float(np.mean(res[:, 2] > 0)),
                          "gap": float(np.median(res[:, 0])), "noise_floor": float(np.median(res[:, 1])),
                          "excess_ci_low": float(np.median(res[:, 2]))})
    return pd.DataFrame(limits, columns=list(LIMIT_COLUMNS)), pd.DataFrame(curve, columns=list(CURVE_COLUMNS))


def verdict_with_limits(verdict: str, limits: pd.DataFrame) -> str:
    """The verdict with the detection limits, e.g. ``none: no effect larger than understory 0.8
    LAI, xy_error 0.15 m; not detectable within the bounds: nonlinearity (up to 50 DN)``.

    Only ``none`` reads "no effect larger than"; another verdict lists the limits as such.
    """
    found = limits[limits["smallest_detectable"].notna()]
    blind = limits[limits["smallest_detectable"].isna()]
    values = ", ".join(f"{r.effect} {r.smallest_detectable:.3g} {r.unit}" for r in found.itertuples())
    parts = []
    if len(found):
        parts.append(("no effect larger than " if verdict == "none" else "detection limits ") + values)
    if len(blind):
        parts.append("not detectable within the bounds: " + ", ".join(
            f"{r.effect} (up to {r.upper_bound:.3g} {r.unit})" for r in blind.itertuples()))
    return f"{verdict}: " + "; ".join(parts) if parts else verdict
