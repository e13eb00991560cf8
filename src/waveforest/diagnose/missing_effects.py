"""The diagnosis without file I/O: search, fresh before/after simulations, signatures, summary.

docs/method.md §(j). :func:`find_missing_effects` runs, from one master seed (the named
stream ``missing_effects``: search, "after" simulations, before/after bootstrap):

1. the search (:func:`.search.search`) on ``keys`` (fits on ``fit_keys``);
2. all pulses simulated again with a fresh seed, independent of the search, under the base
   model and under the extended model (base + named effects; nothing named: "after" is the
   base model), compared with :func:`.before_after.before_after`;
3. the signatures (:func:`signatures`): each candidate near its realistic test value
   (:mod:`waveforest.effects`) against the base model, same seed, from the search's
   simulation cache or from the power analysis' simulations (no new simulation when either
   has the candidate).

:func:`run_diagnosis` is the whole diagnosis of the ``select`` tables: the pulses compared,
their real features, the detection limits (:mod:`.power`), then the above.
:func:`summary_markdown` renders the result as ``diagnose.md``. Gaps in squared pooled SDs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.before_after import before_after
from waveforest.diagnose.gap import sample_universe
from waveforest.diagnose.power import (
    FloorCalibration,
    detection_limits,
    interval_of,
    power_at_test,
    seen_at_test,
    verdict_with_limits,
)
from waveforest.diagnose.replicate_cache import effects_key, simulate_all
from waveforest.diagnose.search import SearchResult, SearchSettings, at_bound, search
from waveforest.diagnose.settings import DiagnoseSettings
from waveforest.diagnose.signature_test import SignatureTest, terms
from waveforest.diagnose.strata import (
    ADDED_STRATA,
    NEAR_STEM_MIN_SAMPLES,
    added_features,
    pulse_keys,
    real_features,
)
from waveforest.diagnose.waveform import with_waveform_statistics
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.rng import named_seeds
from waveforest.stats.bootstrap import bootstrap_weights


def signatures(result: SearchResult, settings: SearchSettings, power_tables: dict | None = None) -> pd.DataFrame:
    """How each candidate near its realistic test value moves the features.

    Against the base model with the same seed (common random numbers): the grid value nearest
    the test value from the search's simulation cache (both halves) when the search simulated
    it; else the value nearest the test value among ``power_tables`` (the power analysis'
    pseudo-real tables, :func:`.power.detection_limits`); else that grid value simulated now.

    Returns
    -------
    DataFrame
        effect, value, test_value and the columns of :func:`.catalogue.signature`.
    """
    sims = result.simulations
    if sims is None:
        return pd.DataFrame()
    power_tables = power_tables or {}
    parts = []
    for name in settings.candidates:
        u_test = cat.to_u(name, CATALOGUE[name].test_value)
        u_grid = cat.grid(name, settings.values)
        u = float(u_grid[np.argmin(np.abs(u_grid - u_test))])
        if abs(u - cat.off_u(name)) < 1e-12:
            continue
        value = cat.from_u(name, u)
        effects = cat.with_effect({}, name, value)
        pairs = {k: t for k, t in power_tables.items() if len(k) == 1 and k[0][0] == name}
        if sims.has(effects) or not pairs:  # the power analysis tests off before any value
            off, on = sims.all({}), sims.all(effects)
        else:
            key = min(pairs, key=lambda k: abs(cat.to_u(name, k[0][1]) - u_test))
            value, off, on = key[0][1], power_tables[effects_key({})], pairs[key]
        try:
            sig = cat.signature(off, on, features=settings.features, floors=settings.floors,
                                min_pulses=settings.min_pulses, min_samples=1)
        except WaveforestError:
            continue
        sig.insert(0, "test_value", CATALOGUE[name].test_value)
        sig.insert(0, "value", value)
        sig.insert(0, "effect", name)
        parts.append(sig)
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


def find_missing_effects(keys: pd.DataFrame, real: pd.DataFrame, simulate, settings: SearchSettings, seed: int, *,
             progress=None, fit_keys: pd.DataFrame | None = None, power_tables: dict | None = None,
             signature: SignatureTest | None = None) -> tuple[SearchResult, pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Search (fits on ``fit_keys``, default all), re-simulate ``keys`` before/after with a
    fresh seed, signatures (no file output; ``power_tables``: see :func:`signatures`).

    The base model's gap is there to explain when its interval lies above the noise floor
    (:func:`base_gap_significant`) or, with ``signature`` (the power analysis'
    :class:`.signature_test.SignatureTest`; ``real`` then carries the whole waveform's
    statistics), when the signature test fires on the same simulation; its reading is the
    result's ``signature``.

    Returns
    -------
    result : SearchResult
    gap : DataFrame
        :func:`.gap.before_after` of the fresh simulations.
    candidates : DataFrame
        The ranked evidence with a ``named`` column (the winner of each round).
    sigs : DataFrame
        :func:`signatures`.
    """
    s_search, s_after, s_boot = named_seeds("missing_effects", int(seed), n=3)
    before = simulate_all(simulate, keys, {}, int(s_after), settings.replicates)
    # the base model's gap as reported decides whether there is a gap to explain
    shown = before_after(real, before, before, n_boot=settings.n_boot, seed=int(s_boot), alpha=settings.alpha,
                         wasserstein=False, **settings.gap_kw)
    reading = None
    if signature is not None:
        universe = sample_universe(real, before)
        reading = signature.read(*terms(real, before, universe, bootstrap_weights(universe, settings.n_boot, int(s_boot)),
                                        floors=settings.floors, min_pulses=settings.min_pulses,
                                        min_samples=settings.min_samples))
    result = search(keys, real, simulate, settings, seed=int(s_search), progress=progress, fit_keys=fit_keys,
                    significant=base_gap_significant(shown) or bool(reading and reading["fires"]),
                    signature=signature)
    result = replace(result, signature=reading)
    after = before if not result.named else simulate_all(simulate, keys, result.effects, int(s_after),
                                                          settings.replicates)
    gap = before_after(real, before, after, n_boot=settings.n_boot, seed=int(s_boot), alpha=settings.alpha,
                            **settings.gap_kw)
    cand = result.candidates.copy()
    if not cand.empty:
        winners = {(e.round, e.name) for e in result.named}
        cand["named"] = [(r, n) in winners for r, n in zip(cand["round"], cand["name"])]
        cand = cand.sort_values(["round", "rank"]).reset_index(drop=True)
    else:
        cand = pd.DataFrame(columns=["round", "rank", "name", "value", "ci_low", "ci_high", "gap_base", "gap_new",
                                     "gap_reduction", "reduction_ci_low", "reduction_ci_high",
                                     "relative_reduction", "significant", "at_bound", "vs_best_ci_low",
                                     "vs_best_ci_high", "named"])
    lead = ["round", "rank", "name", "value", "ci_low", "ci_high", "gap_reduction", "reduction_ci_low",
            "reduction_ci_high", "relative_reduction", "significant", "at_bound", "named"]
    cand = cand[lead + [c for c in cand.columns if c not in lead]]
    return result, gap, cand, signatures(result, settings, power_tables)


def base_gap_significant(gap: pd.DataFrame) -> bool:
    """Whether the base model's total gap in ``gap`` (:func:`.before_after.before_after`) lies
    above its noise floor: the lower bound of its interval above the floor."""
    tot = gap[gap["level"] == "total"].iloc[0]
    return bool(tot["before_ci_low"] > tot["noise_floor"])


def final_verdict(search_verdict: str, limits: pd.DataFrame) -> tuple[str, list[str]]:
    """(verdict of :data:`waveforest.io.results.VERDICTS`, the candidates these data cannot see at their test value).

    ``none`` of the search becomes ``inconclusive`` when the data cannot see a candidate at its
    realistic test value (:func:`.power.seen_at_test` "no": its detection limit is not reached
    or lies beyond the test value, and the power measured there is below the required power
    with its whole interval). A candidate at the "edge" (that interval reaches the required
    power) leaves ``none`` as it is, and the verdict's words name it."""
    blind = [] if limits.empty else limits.loc[seen_at_test(limits) == "no", "effect"].tolist()
    if search_verdict == "none" and blind:
        return "inconclusive", blind
    return search_verdict, blind


def verdict_text(result: SearchResult, limits: pd.DataFrame) -> str:
    """The verdict in words (:func:`final_verdict`, ``verdict.json``'s ``text``): what was named
    with its value and interval, or for ``unexplained`` the best candidate tried, or why no
    candidate could be tried; then the detection limits (:func:`.power.verdict_with_limits`)."""
    verdict = final_verdict(result.verdict, limits)[0]
    lead = ""
    if result.named:
        lead = ", ".join(f"{e.name} {e.value:.3g} [{e.ci_low:.3g}, {e.ci_high:.3g}]" for e in result.named)
    elif result.verdict == "unexplained" and len(result.candidates):
        best = result.candidates.sort_values(["round", "gap_reduction"], ascending=[True, False]).iloc[0]
        lead = (f"a gap that no candidate explains (best fit {best['name']} "
                f"{best['value']:.3g}, reduction {best['gap_reduction']:.3g} [{best['reduction_ci_low']:.3g}, "
                f"{best['reduction_ci_high']:.3g}], not significant)")
    elif result.verdict == "inconclusive":
        lead = "a gap above its noise floor, but too few field samples to fit and test candidates on separate halves"
    return verdict_with_limits(verdict, limits, lead)


def verdict_record(result: SearchResult, gap: pd.DataFrame, limits: pd.DataFrame,
                   floor: FloorCalibration | None = None) -> dict:
    """The machine-readable verdict (``verdict.json``).

    Keys: ``verdict`` (:data:`waveforest.io.results.VERDICTS`), ``search_verdict`` (``model.yaml``'s), ``text`` (the
    verdict with its limits, as in ``diagnose.md``), ``reason``, ``gap`` (the base model's total
    gap, its interval, noise floor, excess and its interval, ``above_floor``: the interval's lower
    bound above the floor), ``named`` (name, value, interval, ``by``: "gap" or "signature", the
    step of :mod:`.search` that named it), ``blind_to`` (per candidate these data cannot see at
    its test value, :func:`.power.seen_at_test` "no": effect, test_value,
    smallest_detectable or null, limit_ci (its interval, null ends as in
    ``detection_limits.csv``), status, upper_bound, unit, power_at_test and its interval, null
    where not measured), ``at_edge`` (the same for the candidates at the "edge"),
    ``floor_calibration`` (``floor``, :class:`.power.FloorCalibration`: scale, the off
    replicates' mean gap and bootstrap floor, replicates), ``signature_test`` (the base model's
    reading, :meth:`.signature_test.SignatureTest.read`; null without the test)."""
    verdict, blind = final_verdict(result.verdict, limits)
    floor = FloorCalibration() if floor is None else floor
    tot = gap[gap["level"] == "total"].iloc[0]
    num = lambda x: None if x is None or not math.isfinite(float(x)) else float(x)  # noqa: E731
    seen = seen_at_test(limits) if len(limits) else pd.Series(dtype=object)

    def unseen(label: str) -> list[dict]:
        return [{"effect": r.effect, "test_value": num(r.test_value), "smallest_detectable":
                 num(r.smallest_detectable), "limit_ci": [num(getattr(r, "limit_ci_low", None)),
                                                          num(getattr(r, "limit_ci_high", None))],
                 "status": r.status, "upper_bound": num(r.upper_bound), "unit": r.unit,
                 "power_at_test": num(getattr(r, "power_at_test", None)),
                 "power_at_test_ci": [num(getattr(r, "power_at_test_ci_low", None)),
                                      num(getattr(r, "power_at_test_ci_high", None))]}
                for r in limits[seen == label].itertuples()] if len(limits) else []
    return {
        "verdict": verdict,
        "search_verdict": result.verdict,
        "text": verdict_text(result, limits),
        "reason": _reason(result, gap),
        "gap": {"total": num(tot["gap_before"]), "ci": [num(tot["before_ci_low"]), num(tot["before_ci_high"])],
                "noise_floor": num(tot["noise_floor"]), "excess": num(tot["gap_before"] - tot["noise_floor"]),
                "excess_ci": [num(tot["before_ci_low"] - tot["noise_floor"]),
                              num(tot["before_ci_high"] - tot["noise_floor"])],
                "above_floor": bool(tot["before_ci_low"] > tot["noise_floor"])},
        "named": [{"name": e.name, "value": float(e.value), "ci": [float(e.ci_low), float(e.ci_high)],
                   "by": "signature" if e.along_signature else "gap"} for e in result.named],
        "blind_to": unseen("no"),
        "at_edge": unseen("edge"),
        "floor_calibration": {"scale": num(floor.scale), "off_gap": num(floor.gap), "off_floor": num(floor.floor),
                              "replicates": int(floor.replicates)},
        "signature_test": result.signature,
    }


@dataclass
class Diagnosis:
    """What :func:`run_diagnosis` found (the tables of :func:`find_missing_effects` and
    :func:`.power.detection_limits`, and the pulses compared)."""

    keys: pd.DataFrame
    fit_keys: pd.DataFrame | None
    result: SearchResult
    gap: pd.DataFrame
    candidates: pd.DataFrame
    signatures: pd.DataFrame
    limits: pd.DataFrame
    curve: pd.DataFrame
    verdict: str = ""
    blind: tuple = ()
    floor: FloorCalibration = field(default_factory=FloorCalibration)


def real_rows(features: pd.DataFrame, keys: pd.DataFrame, selected: dict, metas: dict, strata) -> pd.DataFrame:
    """The real feature rows of ``keys`` (:func:`.strata.pulse_keys`) with the rules applied:
    the comparison pulses' from ``features`` (the real feature tables), those of the strata
    :data:`.strata.ADDED_STRATA` from their rows of ``selected`` (dataset -> table) and
    ``metas`` (dataset -> calibration JSON dict), with the whole waveform's statistics
    (:func:`.waveform.with_waveform_statistics`: the gap may compare them, the signature test
    reads them)."""

    added = keys["stratum"].isin(ADDED_STRATA)
    real = real_features(features, keys[~added], strata)
    if added.any():
        real = pd.concat([real, added_features(keys, selected, metas, strata)], ignore_index=True)
    return with_waveform_statistics(real, selected, metas)


def run_diagnosis(selected: dict, features: pd.DataFrame, metas: dict, simulate, settings: DiagnoseSettings, *,
                  progress=None) -> Diagnosis:
    """The diagnosis of the ``select`` tables ``selected`` (dataset -> pa.Table).

    The pulses compared (:func:`.strata.pulse_keys`; fits on at most ``settings.fit_pulses``
    per dataset x species x stratum), their real rows of ``features`` (the real feature
    tables; the strata under the crowns and in the rings from their rows of ``selected`` and
    ``metas``, dataset -> calibration JSON dict), the detection limits (:func:`.power.detection_limits`), then
    :func:`find_missing_effects` with ``simulate`` (:data:`.replicate_cache.Simulator`),
    whose signatures reuse the power analysis' simulations, with every noise floor
    calibrated on the power analysis' replicates without effect (:func:`.power.floor_calibration`).
    ``progress(label)`` is called after every simulation.
    """

    strata = settings.strata
    keys = pulse_keys(selected, strata)
    fit_keys = None if settings.fit_pulses is None else pulse_keys(selected, strata, int(settings.fit_pulses))
    if keys.empty:
        raise WaveforestError("diagnose: no comparison pulse of the modelled species in the select tables")
    real = real_rows(features, keys, selected, metas, strata)
    power_tables, calibration = {}, {}  # the power analysis' simulations (the signatures reuse them), its floor
    limits, curve = detection_limits(keys, simulate, settings.search, settings.power, settings.seed,
                                     progress=progress, tables=power_tables, calibration=calibration)
    floor = calibration.get("floor", FloorCalibration())
    search_settings = replace(settings.search, floor_scale=floor.scale)
    result, gap, cand, sigs = find_missing_effects(keys, real, simulate, search_settings, settings.seed,
                                                   fit_keys=fit_keys, progress=progress, power_tables=power_tables,
                                                   signature=calibration.get("signature"))
    verdict, blind = final_verdict(result.verdict, limits)
    return Diagnosis(keys=keys, fit_keys=fit_keys, result=result, gap=gap, candidates=cand, signatures=sigs,
                     limits=limits, curve=curve, verdict=verdict, blind=tuple(blind), floor=floor)


def _fmt(x: float, nd: int = 3) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    return f"{x:.{nd}g}"


def summary_markdown(result: SearchResult, gap: pd.DataFrame, cand: pd.DataFrame, *, datasets, n_pulses: int,
                     n_samples: int, seconds: float, settings: SearchSettings, base_effects: dict,
                     limits: pd.DataFrame, curve: pd.DataFrame, n_fit_pulses: int | None = None) -> str:
    """A short human summary (``diagnose.md``); ``limits``, ``curve``: :func:`.power.detection_limits`."""
    tot = gap[gap["level"] == "total"].iloc[0]
    lines = [
        "# Diagnosis: where simulation and measurement disagree",
        "",
        f"**Verdict: {verdict_text(result, limits)}.** "
        f"{(why := _reason(result, gap))[:1].upper()}{why[1:]}.",
        "",
        f"Datasets {', '.join(datasets)}; {n_pulses} real pulses from {n_samples} field samples; "
        f"base model effects {base_effects or 'none (the paper model)'}; {result.n_simulations} half-sample "
        f"simulations in the search ({settings.replicates} simulated pulse(s) per real pulse and value; "
        f"candidates fitted on {n_fit_pulses if n_fit_pulses is not None else n_pulses} pulses, tested on all); "
        f"{seconds:.0f} s.",
        "",
        "The gap is the mean over species (x stratum) x feature of d^2 + ln(SD ratio)^2, d (the mean difference in "
        "pooled SDs) and the log SD ratio each averaged over the datasets first, so that an effect "
        "that moves a species the same way in every dataset adds up (src/waveforest/diagnose/gap.py); "
        "the noise floor is the gap that "
        "sampling noise alone gives (cluster bootstrap over field samples"
        + (f", times {_fmt(settings.floor_scale)}: the mean gap over the mean bootstrap floor of the power "
           "analysis' pseudo-real data without effect, src/waveforest/diagnose/power.py"
           if settings.floor_scale != 1.0 else "")
        + ")."
        + (f" The signature test projects the datasets' mean d and log SD ratio of every first-echo and "
           "whole-waveform statistic on each candidate's signature (its simulation against the base model's), "
           "weighted by their covariance without effect, z "
           "calibrated on the same pseudo-real data, threshold the two-sided family-wise rate "
           f"{_fmt(settings.signature_alpha)} over the candidates (src/waveforest/diagnose/signature_test.py); the "
           "gap is there to explain when its interval lies above the floor or that test fires."
           if settings.signature_alpha is not None else "")
        + " With diagnose.near_stem_m "
        "(default 0.3 m), a tree species' pulses whose first echo lies that close to the stem form the "
        "cells '<species> near stem' (an XY error moves them one way and those further out the other), in the "
        f"datasets where both parts come from at least {NEAR_STEM_MIN_SAMPLES} field samples. With "
        "diagnose.below_crown, a tree species' pulses whose first echo lies lower than "
        "select.tree_min_echo_h_m, the ground seen through gaps in its crowns, form the cells "
        "'<species> below crown'. With diagnose.ring_m (default 0.8 m), the pulses that no sample takes whose "
        "beam meets the ground between select.tree_radius_m and that radius of a compared tree's base, and "
        "whose first echo lies lower than select.tree_min_echo_h_m, form the cells '<species> ground beside': "
        "the ground and what grows on it beside the tree; they compare the first echo's Apeak and E.",
        "",
        f"- base model: gap {_fmt(tot['gap_before'])} [{_fmt(tot['before_ci_low'])}, "
        f"{_fmt(tot['before_ci_high'])}], noise floor {_fmt(tot['noise_floor'])}"
        + (f" (the bootstrap's {_fmt(tot['noise_floor'] / settings.floor_scale)} x {_fmt(settings.floor_scale)}, "
           "calibrated on pseudo-real data without effect)" if settings.floor_scale != 1.0 else ""),
        f"- extended model: gap {_fmt(tot['gap_after'])} [{_fmt(tot['after_ci_low'])}, "
        f"{_fmt(tot['after_ci_high'])}]",
        f"- reduction {_fmt(tot['reduction'])} [{_fmt(tot['reduction_ci_low'])}, "
        f"{_fmt(tot['reduction_ci_high'])}] (fresh simulations, independent of the search)",
        "",
    ]
    if result.named:
        lines += ["## Named effects", "", "| effect | value | 95 % interval | round | test-half gap reduction |",
                  "|---|---|---|---|---|"]
        for e in result.named:
            lines.append(f"| {e.name} | {_fmt(e.value)} | [{_fmt(e.ci_low)}, {_fmt(e.ci_high)}] | {e.round} | "
                         f"{_fmt(e.gap_reduction)} [{_fmt(e.reduction_ci_low)}, {_fmt(e.reduction_ci_high)}] |")
        lines.append("")
        for e in result.named:
            if at_bound(e.name, cat.to_u(e.name, e.value)):
                lines += [f"{e.name} was fitted at the edge of its range: these data do not tell the values "
                          f"from {_fmt(e.ci_low)} to {_fmt(e.ci_high)} apart (a signature that saturates); the "
                          "effect is there, its size known only to lie in that interval.", ""]
            if e.along_signature:
                lines += [f"{e.name} was named {e.along_signature}: its gap reduction on the test halves was "
                          "not significant, the signature test on all samples was."
                          + (f" {', '.join(e.look_alikes)} explain{'s' if len(e.look_alikes) == 1 else ''} "
                             "it along their signatures too: on these data, as good an explanation."
                             if e.look_alikes else ""), ""]
            elif e.look_alikes:
                lines += [f"{', '.join(e.look_alikes)} reduced the gap significantly too in round {e.round}, by an "
                          f"amount not told apart from {e.name}'s: on these data, as good an explanation.", ""]
        model = {**base_effects, **result.effects}
        lines += [f"Use it: `simulate: {{effects: {{{', '.join(f'{k}: {v:.4g}' for k, v in model.items())}}}}}`.",
                  ""]
    if not cand.empty:
        lines += ["## Candidates (best three per round)", "",
                  "| round | rank | effect | value | gap reduction [95 %] | relative | significant |",
                  "|---|---|---|---|---|---|---|"]
        for _, r in cand[cand["rank"] <= 3].iterrows():
            lines.append(f"| {r['round']} | {r['rank']} | {r['name']} | {_fmt(r['value'])} | "
                         f"{_fmt(r['gap_reduction'])} [{_fmt(r['reduction_ci_low'])}, "
                         f"{_fmt(r['reduction_ci_high'])}] | {_fmt(r['relative_reduction'], 2)} | "
                         f"{'yes' if r['significant'] else 'no'}{' (fit at a bound)' if r['at_bound'] else ''} |")
        lines.append("")
    lines += _limits_markdown(limits, curve, result.baseline.noise_floor)
    lines += ["Files: model.yaml (the extended model), candidates.csv (all candidates, ranked), "
              "gap_before_after.csv (per cell, feature and total), gap.png, signatures.csv (how each "
              "candidate moves the features), detection_limits.csv and detection_curve.csv (what these "
              "data could have seen), this summary.", ""]
    return "\n".join(lines)


def _reason(result: SearchResult, gap: pd.DataFrame) -> str:
    """Why the search stopped, worded from the base model's gap as reported in ``gap``."""
    tot = gap[gap["level"] == "total"].iloc[0]
    sig = result.signature
    along = _along(sig) if sig and sig["margin"] is not None else ""
    if result.verdict == "none":
        return (f"the base model's gap {_fmt(tot['gap_before'])} [{_fmt(tot['before_ci_low'])}, "
                f"{_fmt(tot['before_ci_high'])}] is not above its noise floor {_fmt(tot['noise_floor'])} "
                f"(the lower bound of its interval is not above the floor){along}")
    if sig and sig["fires"] and not base_gap_significant(gap):
        return f"the gap's interval reaches its noise floor, but the signature test fires{along}; {result.reason}"
    return f"{result.reason}{along}"


def _along(sig: dict) -> str:
    """The signature test's reading (:meth:`.signature_test.SignatureTest.read`) in words: the
    largest |z| / c and its candidate, the next largest, the threshold."""
    r = sorted(((abs(z) / sig["scale"][e], e) for e, z in sig["z"].items() if z is not None), reverse=True)
    runner = f", then {_fmt(r[1][0])} ({r[1][1]})" if len(r) > 1 else ""
    return f"; along the signatures, the largest |z| / c is {_fmt(r[0][0])} ({r[0][1]}){runner}, threshold {_fmt(sig['threshold'])}"


def _at_bound(r) -> str:
    """``0.45 [0.26, 0.66] at 4 LAI``, or "not tried" (a row of :data:`.power.LIMIT_COLUMNS`)."""
    if pd.isna(r.power_at_bound):
        return "not tried"
    return (f"{_fmt(r.power_at_bound, 2)} [{_fmt(r.power_at_bound_ci_low, 2)}, {_fmt(r.power_at_bound_ci_high, 2)}] "
            f"at {_fmt(r.upper_bound)} {r.unit}")


def _limits_markdown(limits: pd.DataFrame, curve: pd.DataFrame, real_floor: float) -> list[str]:
    """The ``diagnose.md`` section on detection limits (``real_floor``: the real data's noise floor)."""
    reps = int(limits["replicates"].iloc[0]) if len(limits) else 0
    off = curve[curve["strength"] == 0]
    false_alarms = float(off["power"].iloc[0]) if len(off) else math.nan
    fa_ci = (f" [{_fmt(off['power_ci_low'].iloc[0] * 100)}, {_fmt(off['power_ci_high'].iloc[0] * 100)}] %"
             if len(off) and "power_ci_low" in off else "")
    off_floor = float(off["noise_floor"].iloc[0]) if len(off) else math.nan
    lines = ["## What these data could have seen", "",
             f"Each candidate simulated at its test value and at steps towards its limit as pseudo-real data of "
             f"these pulses, {reps} "
             "replicate(s), tested as the base model's gap is (above the noise floor at the same alpha, or the "
             "signature test, same cluster bootstrap); the smallest value detected in at least "
             f"{_fmt(float(limits['power'].iloc[0]) * 100 if len(limits) else math.nan)} % of the replicates "
             f"(src/waveforest/diagnose/power.py). With no effect the test fired in {_fmt(false_alarms * 100)} %{fa_ci} "
             f"of them (95 % Wilson interval). Noise floor of the pseudo-real data without effect {_fmt(off_floor)}, of the real data "
             f"{_fmt(real_floor)}: a real floor well above the pseudo-real one means more spread between real "
             "plants than between simulated ones, and limits that are too small. The pseudo-real data are the "
             "model's own twins: where real data differ from the model in other ways too, an effect at or somewhat "
             "above its limit can still go unnamed (docs/validation.md, Diagnose at the paper's scale).", "",
             "| effect | smallest detectable [95 %] | test value | seen at the test value (power [95 %]) | power at the "
             "range's bound [95 %] (tried when the test value is missed) |", "|---|---|---|---|---|"]
    for r, seen in zip(limits.itertuples(), seen_at_test(limits)):
        found = (f"not reached up to {_fmt(r.upper_bound)} {r.unit}" if pd.isna(r.smallest_detectable)
                 else f"{_fmt(r.smallest_detectable)} {interval_of(r)} {r.unit}".replace("  ", " "))
        lines.append(f"| {r.effect} | {found} | {_fmt(r.test_value)} {r.unit} | "
                     f"{seen}{f' ({p})' if (p := power_at_test(r)) else ''} | {_at_bound(r)} |")
    lines += ["", "Power per value tried: detection_curve.csv and power.png.", ""]
    return lines
