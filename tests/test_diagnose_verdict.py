"""The verdicts of waveforest.diagnose: the gap as reported decides, and "inconclusive" names what
the data cannot see."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from fixtures.study import SyntheticStudy

from waveforest.diagnose.gap import FEATURES, sample_universe
from waveforest.diagnose.missing_effects import (
    base_gap_significant,
    final_verdict,
    find_missing_effects,
    verdict_record,
)
from waveforest.diagnose.power import LIMIT_COLUMNS, FloorCalibration
from waveforest.diagnose.search import SearchSettings, search
from waveforest.diagnose.signature_test import SignatureTest, terms
from waveforest.io.results import VERDICTS

SETTINGS = SearchSettings(features=FEATURES, rounds=1, n_boot=100, candidates=("hotspot", "understory"))


def _limits(seen: dict) -> pd.DataFrame:
    rows = [{"effect": e, "unit": "u", "smallest_detectable": 1.0 if s else np.nan,
             "status": "detected" if s else "not reached", "upper_bound": 2.0, "test_value": 1.5,
             "sees_test_value": s, "power": 0.8, "replicates": 20, "power_at_bound": 1.0 if s else 0.2,
             "power_at_bound_ci_low": 0.0, "power_at_bound_ci_high": 1.0} for e, s in seen.items()]
    return pd.DataFrame(rows, columns=list(LIMIT_COLUMNS))


def test_search_follows_the_significance_it_is_given():
    """The reported gap decides: rounds run when it lies above its floor, whatever the search's
    own baseline says, and none run when it does not."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    hidden = search(study.keys, study.real({"hotspot": 1.3}), study.simulate, SETTINGS, seed=3, significant=False)
    assert hidden.verdict == "none" and hidden.candidates.empty
    nothing = search(study.keys, study.real({}), study.simulate, SETTINGS, seed=3, significant=True)
    assert nothing.verdict != "none" and not nothing.candidates.empty


def test_a_gap_above_its_floor_never_reads_none():
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    for effects in ({}, {"hotspot": 1.3}):
        result, gap, _, _ = find_missing_effects(study.keys, study.real(effects), study.simulate, SETTINGS, seed=5)
        for limits in (_limits({"hotspot": True, "understory": True}), _limits({"hotspot": True, "understory": False})):
            rec = verdict_record(result, gap, limits)
            json.dumps(rec)  # plain JSON
            assert rec["verdict"] in VERDICTS and rec["search_verdict"] == result.verdict
            assert rec["gap"]["above_floor"] == base_gap_significant(gap)
            if rec["gap"]["above_floor"]:
                assert rec["verdict"] in ("named", "unexplained", "inconclusive")
            else:
                assert rec["verdict"] in ("none", "inconclusive")
                assert "not above its noise floor" in rec["reason"]
    assert result.verdict == "named" and result.named[0].name == "hotspot"  # the hidden effect is found
    e = result.named[0]  # the verdict's words name it, with its value and interval, before the limits
    assert rec["text"].startswith(f"named: hotspot {e.value:.3g} [{e.ci_low:.3g}, {e.ci_high:.3g}]; ")


def test_none_becomes_inconclusive_when_an_effect_of_realistic_size_is_not_seen():
    seen, blind = _limits({"hotspot": True, "understory": True}), _limits({"hotspot": True, "understory": False})
    assert final_verdict("none", seen) == ("none", [])
    assert final_verdict("none", blind) == ("inconclusive", ["understory"])
    assert final_verdict("unexplained", blind) == ("unexplained", ["understory"])
    assert final_verdict("named", blind)[0] == "named"


def test_an_effect_at_the_edge_of_the_datas_power_leaves_none_and_is_named():
    """A power at the test value that misses the requirement but whose interval reaches it is
    the replicates' draw, not a claim the data cannot see: the verdict stays none, the record
    lists the candidate under at_edge and the words say so; an interval wholly below it is
    blindness."""
    edge = _limits({"hotspot": True, "understory": False}).assign(
        power_at_test=[1.0, 0.75], power_at_test_ci_low=[0.84, 0.53], power_at_test_ci_high=[1.0, 0.89])
    assert final_verdict("none", edge) == ("none", [])
    assert final_verdict("none", edge.assign(power_at_test_ci_high=[1.0, 0.79])) == ("inconclusive", ["understory"])
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    result, gap, _, _ = find_missing_effects(study.keys, study.real({}), study.simulate, SETTINGS, seed=5)
    assert result.verdict == "none"
    rec = verdict_record(result, gap, edge)
    json.dumps(rec)
    assert rec["verdict"] == "none" and rec["blind_to"] == []
    assert [e["effect"] for e in rec["at_edge"]] == ["understory"]
    assert rec["at_edge"][0]["power_at_test"] == 0.75 and rec["at_edge"][0]["power_at_test_ci"] == [0.53, 0.89]
    assert "at the edge of what these data see: understory at 1.5 u (power 0.75 [0.53, 0.89] there" in rec["text"]


def test_the_calibrated_floor_decides_the_verdict():
    """Every floor the diagnosis reports carries floor_scale; a floor raised above the gap's
    lower bound turns a gap above its floor into none/inconclusive, and the record says why."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    real = study.real({"hotspot": 1.3})
    _, gap1, _, _ = find_missing_effects(study.keys, real, study.simulate, SETTINGS, seed=5)
    tot1 = gap1[gap1["level"] == "total"].iloc[0]
    assert tot1["before_ci_low"] > tot1["noise_floor"]  # the hidden effect clears the bootstrap floor
    scale = 1.5 * tot1["before_ci_low"] / tot1["noise_floor"]  # a floor above the gap's lower bound
    result, gap, _, _ = find_missing_effects(study.keys, real, study.simulate, replace(SETTINGS, floor_scale=scale),
                                             seed=5)
    tot = gap[gap["level"] == "total"].iloc[0]
    assert tot["noise_floor"] == pytest.approx(scale * tot1["noise_floor"])
    assert tot["gap_before"] == pytest.approx(tot1["gap_before"])  # the gap itself is untouched
    cells = gap[gap["level"] == "feature"]["noise_floor"].to_numpy()
    assert np.allclose(cells, scale * gap1[gap1["level"] == "feature"]["noise_floor"].to_numpy())
    rec = verdict_record(result, gap, _limits({"hotspot": True, "understory": True}),
                         FloorCalibration(scale=scale, gap=0.1, floor=0.1 / scale, replicates=20))
    assert result.verdict == "none" and rec["verdict"] == "none" and not rec["gap"]["above_floor"]
    assert rec["floor_calibration"]["scale"] == pytest.approx(scale)


def test_a_firing_signature_test_gives_the_search_a_gap_to_explain():
    """The base model's gap is there to explain when the signature test fires, whatever its
    interval; verdict.json records the test's reading, and a verdict none says how far it was."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    real = study.real({})
    kw = {"min_pulses": SETTINGS.min_pulses, "min_samples": SETTINGS.min_samples}
    sig, _ = terms(study.real({"hotspot": 1.3}), real, sample_universe(real), **kw)
    other, _ = terms(study.real({"understory": 2.5}), real, sample_universe(real), **kw)
    for crit, fires in ((0.0, True), (1e6, False)):
        test = SignatureTest(signatures={"hotspot": sig, "understory": other.reindex(sig.index).fillna(0.0)},
                             null_var=pd.Series(1.0, index=sig.index),
                             null_corr=pd.DataFrame(np.eye(len(sig)), index=sig.index, columns=sig.index),
                             scale={"hotspot": 1.0, "understory": 1.0}, crit=crit)
        result, gap, _, _ = find_missing_effects(study.keys, real, study.simulate, SETTINGS, seed=5, signature=test)
        rec = verdict_record(result, gap, _limits({"hotspot": True, "understory": True}))
        json.dumps(rec)
        reading = rec["signature_test"]
        assert reading["fires"] is fires
        z = {e: abs(v) for e, v in reading["z"].items()}
        best, runner = sorted(z, key=z.get, reverse=True)
        assert reading["effect"] == best
        # every verdict's reason carries the test's reading: the largest |z| / c and the next
        assert f"the largest |z| / c is {z[best]:.3g} ({best}), then {z[runner]:.3g} ({runner})" in rec["reason"]
        if fires:
            assert result.verdict != "none" and not result.candidates.empty
        elif not base_gap_significant(gap):
            assert result.verdict == "none" and "largest |z| / c" in rec["reason"]
