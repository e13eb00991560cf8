"""Detection limits of waveforest.diagnose (power analysis) on the cheap synthetic study."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from fixtures.study import SyntheticStudy

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import FEATURES, gap_report
from waveforest.diagnose.missing_effects import final_verdict
from waveforest.diagnose.power import (
    CURVE_COLUMNS,
    LIMIT_COLUMNS,
    MIN_CALIBRATION_REPLICATES,
    PowerSettings,
    _crossing,
    _crossings,
    _limit,
    _Walk,
    _z_crossing,
    detection_limits,
    floor_calibration,
    seen_at_test,
    verdict_with_limits,
)
from waveforest.diagnose.search import SearchSettings
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.stats.proportion import limit_interval, strongest_tried

SETTINGS = SearchSettings(features=FEATURES, n_boot=100, candidates=("hotspot", "understory"))
POWER = PowerSettings(replicates=3, values=4, power=0.8)


def limits_of(study, simulate=None, settings=SETTINGS, power=POWER, seed=3):
    return detection_limits(study.keys, simulate or study.simulate, settings, power, seed)


def test_every_walk_starts_at_the_test_value_inside_the_range():
    for name in CATALOGUE:  # every effect has a unit, and its test value lies strictly inside the range
        assert cat.UNITS[name]
        w = _Walk.start(name, 3)
        assert w.next == w.test and 0 < w.test < w.bound
        assert w.value(w.test) == pytest.approx(CATALOGUE[name].test_value)
        assert w.value(w.bound) in CATALOGUE[name].bounds and w.value(0.0) == CATALOGUE[name].off
    assert _Walk.start("leaf_albedo", 3).value(_Walk.start("leaf_albedo", 3).bound) == 0.6  # the test value's side
    assert _Walk.start("clumping", 3).value(0.5) == pytest.approx(0.1)  # u = 0.05 / r


def _margins(strength: float, offsets: np.ndarray, scale: float = 0.05) -> np.ndarray:
    """(R, 5) results of a test of one candidate whose margin saturates with strength:
    |z| / c - crit = 30 (1 - exp(-s / scale)) - 3 + offset per replicate (crit 3, z > 0), and
    z / (c crit); the gap never detects."""
    m = 30.0 * (1.0 - math.exp(-strength / scale)) - 3.0 + offsets
    return np.column_stack([np.zeros_like(m), np.ones_like(m), -np.ones_like(m), m, (m + 3.0) / 3.0])


def _walk(values: int, offsets: np.ndarray) -> tuple[_Walk, np.ndarray]:
    w = _Walk.start("hotspot", values)
    off = _margins(0.0, offsets)
    while w.next is not None:
        w.record(_margins(w.next, offsets), off, 16)
    return w, off


def test_the_walk_steps_to_the_limit_that_one_rung_misses():
    """A margin that saturates, as z does: interpolated from the test value alone (one value)
    the limit is several times too large; the walk's steps put a value near it and the limit
    converges on the exact 16th-smallest crossing of the 20 replicates."""
    offsets = np.linspace(-1.0, 1.0, 20)
    exact = np.sort(-0.05 * np.log(1.0 - (3.0 - offsets) / 30.0))[15]
    limits = {}
    for values in (1, 2, 3, 4):
        w, off = _walk(values, offsets)
        assert len(w.rows) == values and w.test in w.rows and w.bound not in w.rows
        strengths = sorted(w.rows)
        assert all(0 < s < w.test for s in strengths[:-1])  # every step below the test value
        limits[values] = _limit(*w.rungs(off), 16)[0]
    assert limits[1] > 3 * exact  # the test value (0.3) is six scales above the limit
    assert abs(limits[3] - exact) < 0.2 * exact and abs(limits[4] - exact) < 0.05 * exact
    assert limits[1] > limits[2] > limits[3] >= limits[4] >= exact  # a concave margin: from above


def test_a_missed_test_value_sends_the_walk_to_the_bound():
    offsets = np.zeros(20)
    w = _Walk.start("hotspot", 3)
    off = _margins(0.0, offsets - 10.0)
    w.record(_margins(w.test, offsets - 30.0), off, 16)  # missed at the test value
    assert w.next == w.bound
    w.record(_margins(w.bound, offsets - 30.0), off, 16)  # and at the bound: not reached
    assert w.next is None and math.isnan(_limit(*w.rungs(off), 16)[0])


def test_crossing_is_exact_for_a_gap_quadratic_in_strength():
    a, c = 3.0, 0.02  # LB(s) = a s^2 - c crosses 0 at sqrt(c / a)
    for lo, hi in ((0.0, 0.25), (0.05, 0.2)):
        assert _crossing(lo, a * lo**2 - c, hi, a * hi**2 - c) == pytest.approx(math.sqrt(c / a))
    assert _crossing(0.1, 0.01, 0.2, 0.05) == 0.1  # detected at the weaker value already
    assert math.isnan(_crossing(0.1, -0.01, 0.2, -0.001))


def test_the_signature_crossing_follows_z_not_its_absolute_value():
    """z / (c crit) of a replicate whose noise points against the effect, -0.6 at off and 1.8 at
    strength 1: it fires at 2/3 (z linear), not at 1/3 (the chord of the margin |w| - 1, -0.4 to
    0.8). With two candidates the first |w| to reach 1 decides, on either side."""
    assert _z_crossing(0.0, np.array([-0.6]), 1.0, np.array([1.8])) == pytest.approx(2 / 3)
    assert _z_crossing(0.2, np.array([0.0, -0.9]), 0.8, np.array([0.5, -1.5])) == pytest.approx(0.2 + 0.6 / 6)
    assert _z_crossing(0.2, np.array([1.1]), 0.8, np.array([2.0])) == 0.2  # fires at the weaker value
    assert math.isnan(_z_crossing(0.2, np.array([0.1, np.nan]), 0.8, np.array([0.9, np.nan])))


def test_crossings_continue_past_a_missed_value():
    """Rungs off, 0.25, 0.5, 1; the limit's interval runs from rung 1 to rung 2 (j = 2). A
    replicate that misses 0.5 crosses between 0.5 and 1 (exactly, for a gap quadratic in
    strength), one that detects 0.25 at 0.25, one that detects nothing at inf."""
    strengths = np.array([0.0, 0.25, 0.5, 1.0])
    a, c = 0.2, 0.1  # replicate 1: LB(s) = a s^2 - c crosses at sqrt(c / a) = 0.707
    lbs = [np.full(4, -0.1), np.array([-0.02, a / 16 - c, 0.01, -0.02]),
           np.array([0.03, a / 4 - c, 0.05, -0.01]), np.array([0.1, a - c, 0.2, -0.005])]
    out = _crossings(strengths, lbs, 2)
    assert out[0] == pytest.approx(_crossing(0.25, -0.02, 0.5, 0.03)) and 0.25 < out[0] < 0.5
    assert out[1] == pytest.approx(math.sqrt(c / a)) and out[2] == 0.25 and out[3] == math.inf
    # rungs below the first interval's lower one need not have been evaluated
    out = _crossings(strengths, [lbs[0], None, lbs[2], lbs[3]], 3)
    np.testing.assert_allclose(out, [0.5, math.sqrt(c / a), 0.5, math.inf])


def test_large_signature_gives_a_monotone_curve_and_a_finite_limit():
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    limits, curve = limits_of(study)
    assert list(limits.columns) == list(LIMIT_COLUMNS) and list(curve.columns) == list(CURVE_COLUMNS)
    assert limits["effect"].tolist() == ["hotspot", "understory"]
    for name in ("hotspot", "understory"):
        row = limits.set_index("effect").loc[name]
        c = curve[curve["effect"] == name].sort_values("strength")
        assert c["strength"].iloc[0] == 0 and c["power"].iloc[0] == 0  # no effect: no detection (these seeds)
        assert np.all(np.diff(c["power"].to_numpy()) >= 0), c  # monotone detection curve
        assert np.all(np.diff(c["excess_ci_low"].to_numpy()) > 0)
        # finite, inside the range, and bracketed by the ladder: detected with power at the next stronger
        # value evaluated, not at the next weaker one (or that one is off)
        v = row["smallest_detectable"]
        s = abs(cat.to_u(name, v) - cat.off_u(name))
        assert 0 < s <= 1 and row["upper_bound"] == CATALOGUE[name].bounds[1]
        above, below = c[c["strength"] >= s - 1e-12], c[c["strength"] < s - 1e-12]
        assert above["power"].iloc[0] >= POWER.power and (below["power"].iloc[-1] < POWER.power
                                                          or below["strength"].iloc[-1] == 0)
        assert v < CATALOGUE[name].test_value  # the realistic value is well visible in this toy
        # the limit's interval: 3 replicates cannot bound a 0.8-quantile from above
        assert 0 <= abs(cat.to_u(name, row["limit_ci_low"]) - cat.off_u(name)) <= s
        assert math.isnan(row["limit_ci_high"])
        assert row["status"] == "detected" and row["sees_test_value"] and row["replicates"] == POWER.replicates
        at_test = c.loc[np.isclose(c["value"], CATALOGUE[name].test_value), "power"]
        assert len(at_test) == 1 and row["power_at_test"] == at_test.iloc[0] >= POWER.power
        # each power with its Wilson interval around it, counted from the replicates
        assert np.all(c["power"] == c["detected"] / POWER.replicates)
        assert np.all((c["power_ci_low"] <= c["power"]) & (c["power"] <= c["power_ci_high"]))
        assert np.all(c["power_ci_high"] - c["power_ci_low"] > 0.3)  # 3 replicates say little


def test_the_ladders_simulate_seed_by_seed_and_give_each_candidates_own_limits():
    """The walks down the candidates' ladders run side by side, each step's simulations grouped
    by pool seed (a seed's base plants then stay in the study's scene cache); without the
    signature test (whose threshold and signatures span the candidates) the limits and curves
    are those of each candidate walked alone."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    seeds = []

    def simulate(keys, effects, seed):
        seeds.append(seed)
        return study.simulate(keys, effects, seed)

    settings = replace(SETTINGS, signature_alpha=None)
    limits, curve = limits_of(study, simulate, settings=settings)
    changes = int(np.count_nonzero(np.diff(seeds)))
    steps = len(curve) - len(limits)  # ladder values tried, over all candidates
    longest = int(curve.groupby("effect").size().max()) - 1
    # the base model's pool, then two switches per step of the walks side by side; one candidate
    # at a time switched seed at every value tried: 2 x steps - 1
    assert changes <= 2 * longest + 1 < 2 * steps - 1
    for name in SETTINGS.candidates:
        alone = replace(settings, candidates=(name,))
        one, one_curve = limits_of(study, settings=alone)
        pd.testing.assert_frame_equal(one, limits[limits["effect"] == name].reset_index(drop=True))
        pd.testing.assert_frame_equal(one_curve, curve[curve["effect"] == name].reset_index(drop=True))


def test_twenty_replicates_bracket_the_limit_with_its_order_statistics():
    """20 replicates at power 0.8: the limit is the 16th smallest crossing, its interval the
    12th and the 20th; the interval brackets the limit and lies within the values tried."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    settings = replace(SETTINGS, candidates=("understory",))
    row = limits_of(study, settings=settings, power=PowerSettings(replicates=20, values=2, power=0.8))[0].iloc[0]
    strength = [abs(cat.to_u("understory", row[k]) - cat.off_u("understory"))
                for k in ("limit_ci_low", "smallest_detectable", "limit_ci_high")]
    assert 0 < strength[0] < strength[1] < strength[2] <= 1, row


def test_a_limit_never_lies_outside_the_values_tried():
    """One replicate, detected only at the bound: the interpolated crossing may not fall beyond
    the weakest value detected; ``smallest_detectable`` lies between off and the bound."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    limits, curve = limits_of(study, power=PowerSettings(replicates=5, values=2, power=0.8))
    for r in limits.itertuples():
        u0 = cat.off_u(r.effect)
        s = abs(cat.to_u(r.effect, r.smallest_detectable) - u0)
        assert 0 < s <= abs(cat.to_u(r.effect, r.upper_bound) - u0) + 1e-12


def test_more_field_samples_see_smaller_effects():
    """With four pool members: from two, the replicates share one difference between them,
    which sets the signature test's scale c as much as the samples do."""
    power = replace(POWER, pool=4)
    few = limits_of(SyntheticStudy(samples_per_species=5, pulses_per_sample=8, seed=1), power=power)[0]
    many = limits_of(SyntheticStudy(samples_per_species=20, pulses_per_sample=8, seed=1), power=power)[0]
    assert (many["smallest_detectable"] < few["smallest_detectable"]).all(), (few, many)


def test_bounds_too_small_to_see_give_an_empty_limit():
    """hotspot made a thousand times weaker: nothing within its bounds (1-2) is detected, the
    ladder stops at the bound, and the limit is empty; understory is untouched."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)

    def damped(pulses, effects, seed):
        eff = dict(effects)
        if "hotspot" in eff:
            eff["hotspot"] = 1.0 + 1e-3 * (eff["hotspot"] - 1.0)
        return study.simulate(pulses, eff, seed)

    limits, curve = limits_of(study, damped)
    hot = limits.set_index("effect").loc["hotspot"]
    assert math.isnan(hot["smallest_detectable"]) and hot["upper_bound"] == 2.0
    assert curve.loc[curve["effect"] == "hotspot", "value"].tolist() == [1.0, 1.3, 2.0]  # off, test value, bound
    assert np.isfinite(limits.set_index("effect").loc["understory", "smallest_detectable"])
    assert hot["status"] == "not reached" and not hot["sees_test_value"] and hot["power_at_bound"] < POWER.power
    text = verdict_with_limits("inconclusive", limits)
    assert text.startswith("inconclusive: these data cannot see hotspot at 1.3 factor (power 0.00 [0.00, 0.56] there, "
                           "not reached up to 2 factor)")
    assert text.endswith("; seen in >= 80% of the model's twins from understory "
                         + f"{limits['smallest_detectable'].iloc[1]:.3g} LAI")
    assert "no effect larger" not in text  # a power on the model's twins, no proof of absence
    assert "side of off only" not in text  # neither effect takes values on both sides of off
    two_sided = limits.assign(effect=limits["effect"].replace({"hotspot": "lad_shift"}))
    assert verdict_with_limits("none", two_sided).endswith("; limits of lad_shift on the test value's side of off only")
    assert verdict_with_limits("named", limits).startswith("named: ")
    assert final_verdict("none", limits) == ("inconclusive", ["hotspot"])
    assert final_verdict("unexplained", limits)[0] == "unexplained"
    assert final_verdict("none", limits[limits["effect"] == "understory"]) == ("none", [])


def test_a_blind_candidates_limit_reads_with_its_interval():
    """A limit beyond its test value is given with the power measured at the test value and the
    limit's interval, whose strong end may lie beyond the strongest value tried: on the far side
    for a value that grows with the effect, below the bound for one that falls as it grows
    (clumping)."""
    assert limit_interval(1.9, math.nan, 4.0) == "[1.9, > 4]" and limit_interval(0.2, 0.41, 0.05) == "[0.2, 0.41]"
    assert limit_interval(math.nan, 0.41, 0.05) == "[< 0.05, 0.41]" and limit_interval(math.nan, math.nan, 4.0) == ""
    # the strongest value tried: the bound where it was (its power measured), else the test value
    assert strongest_tried(4.0, 2.5, 0.9) == 4.0 and strongest_tried(4.0, 2.5, math.nan) == 2.5
    assert strongest_tried(4.0, math.nan, math.nan) == 4.0  # a table without test values
    limits = pd.DataFrame([
        {"effect": "understory", "unit": "LAI", "smallest_detectable": 3.18, "limit_ci_low": 1.92,
         "limit_ci_high": math.nan, "status": "detected", "upper_bound": 4.0, "test_value": 2.5,
         "sees_test_value": False, "power": 0.8, "replicates": 20, "power_at_bound": 0.9,
         "power_at_bound_ci_low": 0.7, "power_at_bound_ci_high": 0.97, "power_at_test": 0.75,
         "power_at_test_ci_low": 0.53, "power_at_test_ci_high": 0.89},
        {"effect": "clumping", "unit": "m", "smallest_detectable": 0.28, "limit_ci_low": 0.2,
         "limit_ci_high": 0.41, "status": "detected", "upper_bound": 0.05, "test_value": 0.15,
         "sees_test_value": True, "power": 0.8, "replicates": 20, "power_at_bound": 1.0,
         "power_at_bound_ci_low": 0.84, "power_at_bound_ci_high": 1.0}], columns=list(LIMIT_COLUMNS))
    assert verdict_with_limits("none", limits) == (
        "none: at the edge of what these data see: understory at 2.5 LAI (power 0.75 [0.53, 0.89] there, "
        "limit 3.18 [1.92, > 4] LAI); "
        "seen in >= 80% of the model's twins from clumping 0.28 m")
    weak = limits.assign(power_at_test=[0.45, math.nan], power_at_test_ci_low=[0.26, math.nan],
                         power_at_test_ci_high=[0.66, math.nan])
    assert verdict_with_limits("inconclusive", weak) == (
        "inconclusive: these data cannot see understory at 2.5 LAI (power 0.45 [0.26, 0.66] there, "
        "limit 3.18 [1.92, > 4] LAI); "
        "seen in >= 80% of the model's twins from clumping 0.28 m")


def test_seen_at_test_claims_blindness_only_on_a_power_interval_below_the_requirement():
    """"no" needs the power measured at the test value to miss the requirement with its whole
    interval (or no power measured there); a limit at or below the test value is "yes"."""
    rows = pd.DataFrame({"sees_test_value": [True, False, False, False, False], "power": 0.8,
                         "smallest_detectable": [1.0, 3.0, 3.0, math.nan, 3.0],
                         "power_at_test": [0.9, 0.75, 0.45, math.nan, 0.7],
                         "power_at_test_ci_low": [0.7, 0.53, 0.26, math.nan, 0.48],
                         "power_at_test_ci_high": [0.97, 0.89, 0.66, math.nan, 0.8]})
    assert seen_at_test(rows).tolist() == ["yes", "edge", "no", "no", "edge"]
    assert seen_at_test(rows.drop(columns=["power_at_test_ci_high"])).tolist() == ["yes", "no", "no", "no", "no"]
    old = rows[["smallest_detectable"]]  # a table from before the test value was a column
    assert seen_at_test(old).tolist() == ["yes", "yes", "yes", "no", "yes"]


def test_power_settings_are_checked_and_read_from_the_config():
    from waveforest import config
    from waveforest.settings import diagnose_settings

    assert diagnose_settings(config.load()).power == PowerSettings()
    assert PowerSettings(replicates=3, power=0.8).needed == 3 and PowerSettings(replicates=5, power=0.8).needed == 4
    with pytest.raises(WaveforestError, match="diagnose.power"):
        PowerSettings(replicates=0)
    study = SyntheticStudy(samples_per_species=3, pulses_per_sample=2)
    limits, curve = detection_limits(study.keys, None, SearchSettings(features=FEATURES, candidates=()), POWER, 1)  # all in the model
    assert limits.empty and list(limits.columns) == list(LIMIT_COLUMNS) and verdict_with_limits("none", limits) == "none"
    with pytest.raises(WaveforestError, match="no pulse"):
        detection_limits(pd.DataFrame(columns=["dataset", "sample_id", "species"]), None, SETTINGS, POWER, 1)


def test_floor_calibration_is_the_mean_off_gap_over_the_mean_bootstrap_floor():
    off = np.array([[0.02, 0.01, -0.1], [0.04, 0.01, 0.0]] * MIN_CALIBRATION_REPLICATES)
    cal = floor_calibration(off)
    assert cal.scale == pytest.approx(3.0) and cal.gap == pytest.approx(0.03) and cal.floor == pytest.approx(0.01)
    assert cal.replicates == 2 * MIN_CALIBRATION_REPLICATES
    assert floor_calibration(off[: MIN_CALIBRATION_REPLICATES - 1]).scale == 1.0  # too few: not calibrated
    assert floor_calibration(np.array([[np.nan, 0.01, 0.0]] * 9)).scale == 1.0


def test_the_calibrated_floor_is_the_no_effect_gap_on_fresh_data():
    """Three field samples per species: the bootstrap floor misjudges the gap that data without
    effect give; the floor calibrated on the power analysis' replicates matches it on fresh,
    independent data without effect (not those it was calibrated on)."""
    study = SyntheticStudy(samples_per_species=3, pulses_per_sample=8, seed=1)
    cal = {}
    detection_limits(study.keys, study.simulate, replace(SETTINGS, candidates=("hotspot",)),
                     PowerSettings(replicates=10, values=1, pool=4), 3, calibration=cal)
    scale = cal["floor"].scale
    gaps, floors = [], []
    for k in range(12):
        real = study.simulate(study.keys, {}, 1000 + k).assign(source="real")
        for fs, out in ((1.0, floors), (scale, None)):
            rep = gap_report(real, study.simulate(study.keys, {}, 2000 + k), n_boot=100, seed=k, wasserstein=False,
                             features=FEATURES, floor_scale=fs).summary.loc["total"]
            if out is not None:
                out.append(rep["noise_floor"])
            else:
                assert rep["noise_floor"] == pytest.approx(scale * floors[-1])  # the factor, nothing else
        gaps.append(rep["gap"])
    raw, calibrated = np.mean(gaps) / np.mean(floors), np.mean(gaps) / (scale * np.mean(floors))
    assert abs(np.log(raw)) > 0.25  # the bootstrap floor is off here ...
    assert abs(np.log(calibrated)) < 0.6 * abs(np.log(raw)) and 0.75 < calibrated < 1.33  # ... the calibrated one holds
