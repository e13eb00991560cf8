"""Outputs of the diagnose stage: model.yaml, tables, figure; the CLI; the real chain (slow)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from click.testing import CliRunner
from fixtures.study import SyntheticStudy

from waveforest.constants import RANGE_PER_NS
from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import FEATURES
from waveforest.diagnose.missing_effects import find_missing_effects
from waveforest.diagnose.power import LIMIT_COLUMNS, PowerSettings, detection_limits
from waveforest.diagnose.search import NamedEffect, SearchSettings
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.io.results import model_dict, read_model, write_model
from waveforest.report.summary import diagnosis_text
from waveforest.settings import diagnose_settings
from waveforest.stages.diagnose import OUTPUT_NAMES, write_outputs

ROOT = Path(__file__).resolve().parents[1]


def _synthetic_outputs(tmp_path, effects):
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    settings = SearchSettings(features=FEATURES, rounds=2, n_boot=100)
    tables = {}  # as the stage runs them: the power analysis first, its simulations reused
    limits, curve = detection_limits(study.keys, study.simulate, settings, PowerSettings(replicates=2, values=3), 5,
                                     tables=tables)
    result, gap, cand, sigs = find_missing_effects(study.keys, study.real(effects), study.simulate, settings, seed=5,
                                                   power_tables=tables)
    paths = write_outputs(tmp_path, result, gap, cand, sigs, limits=limits, curve=curve, settings=settings,
                          base_effects={}, datasets=sorted(study.datasets), keys=study.keys, seconds=1.0)
    return result, paths


def _strata(**diagnose):
    """The StrataSettings of the default study with these ``diagnose`` keys."""
    from waveforest import config

    return diagnose_settings(config.load(overrides={"diagnose": diagnose})).strata


def _select_table(rows):
    import pyarrow as pa

    return pa.Table.from_pandas(pd.DataFrame(rows), preserve_index=False)


def test_pulses_under_the_crowns_are_a_stratum_with_the_mirror_rule():
    """With diagnose.below_crown, below_crown_set pulses join the diagnosis as the stratum
    "below crown", capped on their own; a twin stays in its pulse's stratum only when its first echo meets the same height
    rule, and compare's height rule blanks the waveform features of low crown pulses only."""
    from waveforest.diagnose.strata import BELOW_CROWN, apply_rules, pulse_keys

    base = dict(dataset="2010_12_1", species="birch", is_tree=True)
    rows = [dict(base, pulse_id=i, sample_id=f"s{i % 3}", comparison_set=i < 20, below_crown_set=i >= 20)
            for i in range(26)]
    rows.append(dict(base, pulse_id=99, sample_id="s9", species="pine", comparison_set=False, below_crown_set=True))
    off = pulse_keys({"2010_12_1": _select_table(rows)}, _strata())
    assert off["pulse_id"].tolist() == list(range(20)) and (off["stratum"] == "").all()
    strata = _strata(below_crown=True)
    keys = pulse_keys({"2010_12_1": _select_table(rows)}, strata)
    assert keys.set_index("pulse_id")["stratum"].to_dict() == {i: BELOW_CROWN if i >= 20 else "" for i in range(26)}
    capped = pulse_keys({"2010_12_1": _select_table(rows)}, strata, cap=4)
    assert capped.groupby("stratum").size().to_dict() == {"": 4, BELOW_CROWN: 4}
    lo, hi = strata.rules.tree_min_echo_h_m, strata.compare_min_h_m["birch"]
    feats = pd.DataFrame({"species": ["birch"] * 6 + ["raspberry"], "is_tree": [True] * 6 + [False],
                          "stratum": ["", "", "", BELOW_CROWN, BELOW_CROWN, ""] + [""],
                          "H": [lo - 0.1, lo + 0.1, hi + 0.1, lo - 0.1, lo + 0.1, np.nan, 0.2], "E": 500.0})
    out = apply_rules(feats, strata)
    assert out["H"].tolist() == pytest.approx([lo + 0.1, hi + 0.1, lo - 0.1, 0.2])
    assert out["E"].isna().tolist() == [True, False, False, False]


def test_tree_pulses_near_the_stem_are_a_stratum_of_the_same_pulses():
    """diagnose.near_stem_m splits a tree species' comparison pulses by the first echo's distance
    from the stem where both parts come from enough field samples (not in a dataset of 7 birches);
    herbs and the stratum under the crowns keep theirs, and the split comes after the caps: the
    same pulses of the same samples with and without it."""
    from waveforest.diagnose.strata import BELOW_CROWN, NEAR_STEM, NEAR_STEM_MIN_SAMPLES, pulse_keys

    def birches(ds, n_samples, first_id):
        return [dict(dataset=ds, pulse_id=first_id + i, sample_id=f"{ds}s{i % n_samples}", species="birch",
                     is_tree=True, comparison_set=i < 40, below_crown_set=i >= 40,
                     sample_distance_m=0.5 * ((i * 0.37) % 1.0)) for i in range(46)]

    rows = birches("2010_12_1", 20, 0) + birches("2012_10_1", 7, 1000)
    rows += [dict(dataset="2010_12_1", pulse_id=100 + i, sample_id=f"r{i % 3}", species="raspberry", is_tree=False,
                  comparison_set=True, below_crown_set=False, sample_distance_m=0.05) for i in range(12)]
    tables = {ds: _select_table([r for r in rows if r["dataset"] == ds]) for ds in ("2010_12_1", "2012_10_1")}
    near = {r["pulse_id"]: r["sample_distance_m"] < 0.3 for r in rows}
    split = [r for r in rows if r["dataset"] == "2010_12_1" and r["species"] == "birch" and r["comparison_set"]]
    for part in (True, False):  # the premise: both parts of 2010_12_1's birches are well sampled
        assert len({r["sample_id"] for r in split if near[r["pulse_id"]] == part}) >= NEAR_STEM_MIN_SAMPLES

    def keys(**diagnose):
        return pulse_keys(tables, _strata(below_crown=True, **diagnose)).set_index(
            "pulse_id")

    on, off = keys(), keys(near_stem_m=None)
    want = {r["pulse_id"]: "" for r in rows}
    want.update({r["pulse_id"]: BELOW_CROWN for r in rows if r["below_crown_set"]})
    want.update({r["pulse_id"]: NEAR_STEM for r in split if near[r["pulse_id"]]})
    assert on["stratum"].to_dict() == want and 0 < list(want.values()).count(NEAR_STEM) < 40
    assert (off["stratum"] != NEAR_STEM).all()
    assert on.drop(columns="stratum").equals(off.drop(columns="stratum"))
    for cap in (10, 25):
        assert keys(pulses_per_species=cap).index.tolist() == keys(pulses_per_species=cap, near_stem_m=None).index.tolist()
    # the fit subset (a cap per species) keeps the whole's cells, though its own parts are smaller
    fit = pulse_keys(tables, _strata(below_crown=True), cap=8).set_index("pulse_id")
    assert fit["stratum"].to_dict() == {i: want[i] for i in fit.index} and (fit["stratum"] == NEAR_STEM).any()


def test_a_blurred_crown_profile_cancels_in_one_cell_and_shows_split_at_the_stem():
    """Why diagnose.near_stem_m: an XY error blurs a conical crown's first-echo heights, and
    select's height rule drops echoes blurred off the crown. Pulses recorded near the stem then
    echo lower than their twins and those further out higher; in one cell the shifts cancel,
    split at the stem each shows, and the gap is several times larger."""
    from waveforest.diagnose import gap as G
    from waveforest.diagnose.strata import NEAR_STEM

    rng = np.random.default_rng(8)
    rows = []
    for ds in ("a", "b", "c"):
        for j in range(60):
            top = rng.uniform(3.0, 5.0)  # a cone of height top and radius 0.6 m, pulses within 0.5 m
            r = 0.5 * np.sqrt(rng.uniform(size=(2, 40)))  # recorded distances, real and twin pulses
            blur = np.hypot(r[0] * np.cos(t := rng.uniform(0, 2 * np.pi, 40)) + 0.2 * rng.standard_normal(40),
                            r[0] * np.sin(t) + 0.2 * rng.standard_normal(40))
            for src, rec, true in (("real", r[0], blur), ("sim", r[1], r[1])):
                h = top * (1.0 - true / 0.6) + 0.05 * rng.standard_normal(40)
                keep = h >= 1.0
                rows.append(pd.DataFrame({"src": src, "dataset": ds, "species": "birch", "sample_id": f"{ds}{j}",
                                          "stratum": np.where(rec < 0.3, NEAR_STEM, ""), "H": h})[keep])
    df = pd.concat(rows, ignore_index=True)
    real, sim = df[df.src == "real"].drop(columns="src"), df[df.src == "sim"].drop(columns="src")

    def gap(split):
        r, s = (t if split else t.drop(columns="stratum") for t in (real, sim))
        return G.total_gap(G.GapData.build(r, s, features=("H",)))

    d = {lab: (sim[sim.stratum == lab].H.mean() - real[real.stratum == lab].H.mean()) for lab in (NEAR_STEM, "")}
    assert d[NEAR_STEM] > 0 > d[""]
    assert gap(True) > 3 * gap(False)


def test_pulses_per_species_keeps_whole_samples_the_same_in_every_dataset_and_nested():
    """diagnose.pulses_per_species: whole field samples per dataset x species, in one seeded order
    of the samples for every dataset, at most the dataset's share of the budget (the budget over
    the datasets, rounded up; at least the two samples a compared cell needs); a smaller budget
    keeps a subset of a larger one's samples; null keeps every comparison pulse; fewer datasets
    spend the same budget on more samples of each."""
    from waveforest.diagnose.strata import pulse_keys

    rng = np.random.default_rng(3)
    sizes = rng.integers(1, 9, 40)
    tables = {}
    for ds in ("2012_05_1", "2012_10_1"):
        rows, pid = [], 0
        for k, n in enumerate(sizes):
            for _ in range(int(n)):
                rows.append(dict(dataset=ds, pulse_id=pid, sample_id=f"s{k}", species="raspberry", is_tree=False,
                                 comparison_set=True, below_crown_set=False))
                pid += 1
        tables[ds] = _select_table(rows)

    def keys(budget, datasets=tables):
        return pulse_keys(datasets, _strata(pulses_per_species=budget))

    every = keys(None)
    assert len(every) == 2 * sizes.sum()
    samples = {}
    for budget in (1, 24, 60, 120):
        k = keys(budget)
        by = k.groupby("dataset")
        assert (by.size() <= max(-(-budget // 2), 2 * sizes.max())).all()
        per_ds = [set(g["sample_id"]) for _, g in by]
        assert per_ds[0] == per_ds[1]  # the same samples in both datasets (same pulses per sample here)
        counts = k.groupby(["dataset", "sample_id"]).size()
        assert (counts.to_numpy() == sizes[[int(s[1:]) for _, s in counts.index]]).all()  # whole samples
        samples[budget] = per_ds[0]
        alone = keys(budget, {"2012_10_1": tables["2012_10_1"]})  # one dataset: the whole budget
        assert len(alone) <= max(budget, 2 * sizes.max()) and set(alone["sample_id"]) >= per_ds[1]
        if budget >= 24:
            assert len(alone) > by.size().max() and abs(len(alone) - len(k)) <= sizes.max()
    assert samples[1] <= samples[24] <= samples[60] <= samples[120] and len(samples[1]) == 2
    assert len(samples[120]) < 40
    # a cell of three samples whose second overflows the budget keeps two, enough to be compared
    rows = [dict(dataset="2012_10_1", pulse_id=i, sample_id=f"t{i // 50}", species="fireweed", is_tree=False,
                 comparison_set=True, below_crown_set=False) for i in range(150)]
    assert pulse_keys({"2012_10_1": _select_table(rows)}, _strata(pulses_per_species=60))["sample_id"].nunique() == 2


def test_pulses_per_species_keeps_samples_that_differ_between_seeds_as_independent_draws():
    """The samples that a cap keeps under different master seeds overlap as independent random
    subsets would. An order by a CRC-32 of seed and id is affine in the id's bits: of the 45 pairs
    of seeds 2014-2023, 37 then share none of their 80 samples and four 68 or 72."""
    from dataclasses import replace

    from waveforest.diagnose.strata import pulse_keys

    ids = [f"2012-{stand:02d}-{k:03d}" for stand in range(1, 15) for k in range(1, 41)]
    rows = [dict(dataset="2012_10_1", pulse_id=i, sample_id=s, species="raspberry", is_tree=False,
                 comparison_set=True, below_crown_set=False) for i, s in enumerate(ids)]
    table = {"2012_10_1": _select_table(rows)}
    base = _strata(pulses_per_species=80)
    kept = [set(pulse_keys(table, replace(base, seed=s))["sample_id"]) for s in range(2014, 2024)]
    assert all(len(k) == 80 for k in kept)
    overlap = [len(a & b) for i, a in enumerate(kept) for b in kept[i + 1:]]
    # 80 of 560 drawn independently twice share 11.4 samples on average (hypergeometric SD 2.9)
    assert 9 <= np.mean(overlap) <= 14 and min(overlap) >= 3 and max(overlap) <= 25, overlap


def test_real_below_crown_echoes_are_found_as_a_twins_are():
    """own_cfd_echoes arms the CFD on the recorded noise, SD / AGC gain, as render_sigma does
    for a twin: a weak early return under the arming level at gain 1 is the first echo at
    gain 4; a pulse without a CFD echo is left out, as a twin without one is."""
    import pyarrow as pa
    from fixtures.tables import pulse_table

    from waveforest import config
    from waveforest.diagnose.strata import own_cfd_echoes
    from waveforest.io.pulses import padded_to_list
    from waveforest.sensor import gaussian_system_waveform
    from waveforest.sensor.calibration import Calibration
    from waveforest.settings import sensor_settings

    mean, sd, t = 10.0, 1.0, np.arange(120.0)

    def echo(t0, amplitude):
        return amplitude * np.exp(-4 * np.log(2) * ((t - t0) / 7.0) ** 2)

    weak_then_strong = mean + echo(30.0, 2.5 * sd) + echo(60.0, 50.0)  # 2.5 SD: under the 4-SD arming
    rows = np.vstack([weak_then_strong, weak_then_strong, np.full_like(t, mean)]).astype(np.float32)
    table = pulse_table("d", [[(0.0, 0.0, 0.0)]] * 3)
    table = table.set_column(table.schema.get_field_index("samples"), "samples",
                             padded_to_list(rows, np.full(3, len(t)), pa.float32()))
    table = table.append_column("agc_gain", pa.array([1.0, 4.0, 1.0]))
    out = own_cfd_echoes(table, Calibration(gaussian_system_waveform(7.0, 1.0), mean, sd),
                         sensor_settings(config.load()))
    assert out.column("pulse_id").to_pylist() == [0, 1]
    first = [e[0] for e in out.column("echo_time_ns").to_pylist()]
    assert first == pytest.approx([60.0, 30.0], abs=1.0)
    assert out.column("n_echoes").to_pylist() == [1, 2]
    anchor_z = table.column("anchor_z").to_numpy()[:2]  # positions on the beam line (nadir)
    z = [e[0] for e in out.column("echo_z").to_pylist()]
    assert z == pytest.approx(anchor_z - np.array(first) * RANGE_PER_NS, abs=1e-6)


def test_pulses_under_the_crowns_are_chosen_by_their_own_cfd_echo():
    """with_pulses_under_crowns re-draws below_crown_set with select's rules on each pulse's own
    CFD echoes: a pulse whose DR echo missed the tree joins when its waveform's first echo lies
    under the crown, and so does one whose DR fired on a crown return its waveform does not
    show; one the DR put there leaves when its waveform shows the crown first; a crown pulse by
    both stays. The rows carry their CFD echo positions."""
    from fixtures.tables import pulse_table

    from waveforest.diagnose.strata import with_pulses_under_crowns
    from waveforest.model.selection import select_pulses
    from waveforest.sensor import gaussian_system_waveform
    from waveforest.sensor.calibration import Calibration

    fields = pd.DataFrame([dict(sample_id="T1", year=2010, species="birch", functional_group="broadleaf", x=0.0,
                                y=0.0, ground_z=100.0, height_m=3.0, radius_m=0.5, is_tree=True)])
    truth = [[(0.1, 0.0, 100.0)], [(0.2, 0.0, 101.5), (0.2, 0.0, 100.0)], [(0.0, 0.1, 102.0)],
             [(0.0, -0.1, 100.0)]]
    seen_by_dr = [[(3.0, 0.0, 102.0)], [(0.2, 0.0, 100.0)], [(0.0, 0.1, 102.0)], [(0.0, -0.1, 101.5)]]
    agc = pulse_table("2010_12_1", truth)
    dr = pulse_table("2010_12_1", seen_by_dr)
    for name in ("n_echoes", "echo_x", "echo_y", "echo_z", "echo_time_ns", "echo_intensity"):
        agc = agc.set_column(agc.schema.get_field_index(name), name, dr.column(name))
    strata = _strata()
    selected = select_pulses(agc, fields, 2010, strata.rules)
    assert selected.column("pulse_id").to_pylist() == [1, 2, 3]  # by the DR: 1 under the crown, 2 and 3 in it
    assert selected.column("below_crown_set").to_pylist() == [True, False, False]
    out = with_pulses_under_crowns(selected, agc, fields, 2010, Calibration(gaussian_system_waveform(7.0, 1.0),
                                                                             10.0, 1.0), strata).to_pandas()
    assert out.set_index("pulse_id")["below_crown_set"].to_dict() == {2: False, 0: True, 3: True}
    own = out[out["pulse_id"] == 0].iloc[0]
    assert own["echo_z"][0] == pytest.approx(100.0, abs=0.05) and own["first_echo_h_m"] == pytest.approx(0.0, abs=0.05)
    assert out.columns.tolist() == selected.column_names


def test_a_beam_turned_about_its_stem_keeps_heights_and_distances():
    """turned_about_stems turns sensor, anchor and direction about the sample's vertical axis:
    every point of the beam keeps its height and its distance from the stem (stem_distance)."""
    from fixtures.tables import pulse_table

    from waveforest.diagnose.strata import stem_distance, turned_about_stems

    t = pulse_table("d", [[(1.0, 0.5, 100.0)], [(2.0, -1.0, 100.0)]])
    t = t.append_column("sample_x", pa_array([0.5, 2.0])).append_column("sample_y", pa_array([0.0, 0.0]))
    tilt = {"dir_x": [0.3, -0.2], "dir_y": [0.1, 0.25]}  # off-nadir beams
    for name, v in tilt.items():
        t = t.set_column(t.schema.get_field_index(name), name, pa_array(v))
    z = np.array([[100.0, 100.0], [100.8, 101.5], [99.5, 100.3]])
    turned = turned_about_stems(t, [np.pi / 2, 2.0])
    for row in z:
        assert stem_distance(turned, row) == pytest.approx(stem_distance(t, row))
    assert turned.column("sensor_z").to_pylist() == t.column("sensor_z").to_pylist()
    # a quarter turn about (0.5, 0): the sensor above (1.0, 0.5) goes above (0.0, 0.5)
    assert turned.column("sensor_x").to_pylist()[0] == pytest.approx(0.0)
    assert turned.column("sensor_y").to_pylist()[0] == pytest.approx(0.5)
    assert (turned.column("dir_x").to_pylist()[0], turned.column("dir_y").to_pylist()[0]) == pytest.approx((-0.1, 0.3))
    # at the sensor's own height the distance is the sensor's
    assert stem_distance(t, t.column("sensor_z").to_numpy())[0] == pytest.approx(np.hypot(0.5, 0.5))


def pa_array(values):
    import pyarrow as pa

    return pa.array(np.asarray(values, float))


def test_outputs_of_a_named_effect(tmp_path):
    result, paths = _synthetic_outputs(tmp_path, {"hotspot": 1.3})
    assert {p.name for p in tmp_path.iterdir()} == set(OUTPUT_NAMES.values())
    m = read_model(paths["model"])
    assert m["verdict"] == "named"
    assert [e["name"] for e in m["effects"]] == ["hotspot"]
    e = m["effects"][0]
    assert e["ci_low"] <= 1.3 <= e["ci_high"] and e["gap_reduction"] > 0
    assert m["simulate_effects"] == {"hotspot": e["value"]}
    gap = pd.read_csv(paths["gap"])
    tot = gap[gap["level"] == "total"].iloc[0]
    # "after" is a fresh simulation with the named model: the gap at least halves
    assert tot["gap_after"] <= 0.5 * tot["gap_before"] and tot["reduction_ci_low"] > 0
    assert set(gap.loc[gap["level"] == "feature", "feature"]) == {"H", "Npeaks", "Apeak", "FWHM", "E"}
    cand = pd.read_csv(paths["candidates"])
    for col in ("round", "name", "value", "ci_low", "ci_high", "gap_reduction", "reduction_ci_low",
                "reduction_ci_high", "significant", "named"):
        assert col in cand.columns
    assert cand.loc[cand["named"], "name"].tolist() == ["hotspot"]
    sig = pd.read_csv(paths["signatures"])
    # hotspot's toy signature: Apeak up, FWHM down, H untouched (common random numbers)
    h = sig[sig["effect"] == "hotspot"]
    hs = h.groupby("feature")["shift_sd"].mean()
    assert hs["Apeak"] > 0.3 and hs["FWHM"] < 0 and abs(hs["H"]) < 1e-9
    fwhm = h[h["feature"] == "FWHM"]  # the toy's FWHM shift is exactly -0.8 (k - 1)
    assert (fwhm["mean_on"] - fwhm["mean_off"]).to_numpy() == pytest.approx(-0.8 * (h["value"].iloc[0] - 1.0))
    assert paths["figure"].stat().st_size > 10_000
    assert "hotspot" in paths["markdown"].read_text()


def test_outputs_when_nothing_is_named(tmp_path):
    result, paths = _synthetic_outputs(tmp_path, {})
    m = yaml.safe_load(paths["model"].read_text())
    assert m["verdict"] == "none" and m["effects"] == []
    gap = pd.read_csv(paths["gap"])
    assert (gap["reduction"] == 0).all()  # after = before
    # detection_limits.csv: the report's contract; every candidate, a number or an empty cell
    limits = pd.read_csv(paths["limits"])
    assert list(limits.columns) == list(LIMIT_COLUMNS)
    assert limits["effect"].tolist() == list(CATALOGUE) and (limits["replicates"] == 2).all()
    assert (limits["power"] == 0.8).all() and limits["unit"].notna().all()
    assert (limits["upper_bound"] != [CATALOGUE[e].off for e in limits["effect"]]).all()
    assert limits["smallest_detectable"].notna().sum() >= 5  # the toy's signatures are large
    found = limits.dropna(subset=["smallest_detectable"])
    strength = [abs(cat.to_u(e, v) - cat.off_u(e)) for e, v in zip(found["effect"], found["smallest_detectable"])]
    reach = [abs(cat.to_u(e, v) - cat.off_u(e)) for e, v in zip(found["effect"], found["upper_bound"])]
    assert all(0 < s <= r for s, r in zip(strength, reach))
    curve = pd.read_csv(paths["curve"])
    assert set(curve["effect"]) == set(CATALOGUE) and (curve["power"].between(0, 1)).all()
    md = paths["markdown"].read_text()
    assert "**Verdict: none: seen in >= 80% of the model's twins from " in md and "What these data could have seen" in md
    assert ".** The base model's gap " in md  # the reason is a sentence of its own
    verdict = json.loads(paths["verdict"].read_text())  # the report shows the diagnosis's verdict, not the search's
    assert diagnosis_text(tmp_path).startswith(f"Diagnosis — verdict: {verdict['text']} ({verdict['reason']})")


def test_signatures_reuse_the_power_analysis_when_nothing_was_searched():
    """With nothing to search, the signatures come from the power analysis' pseudo-real
    simulations (one seed: common random numbers), not from new simulations."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    settings = SearchSettings(features=FEATURES, rounds=2, n_boot=100)
    calls = []

    def counted(pulses, effects, seed):
        calls.append(dict(effects))
        return study.simulate(pulses, effects, seed)

    tables = {}
    detection_limits(study.keys, counted, settings, PowerSettings(replicates=1, values=2), 5, tables=tables)
    n_power = len(calls)
    result, _, _, sigs = find_missing_effects(study.keys, study.real({}), counted, settings, seed=5,
                                              power_tables=tables)
    assert result.verdict == "none"
    assert calls[n_power:] and all(not c for c in calls[n_power:])  # base model only after the power analysis
    assert set(sigs["effect"]) == set(settings.candidates)
    for name, g in sigs.groupby("effect"):  # the value tried nearest the test value, in the search coordinate
        tried = [k[0][1] for k in tables if k and k[0][0] == name]
        u_test = cat.to_u(name, CATALOGUE[name].test_value)
        assert g["value"].iloc[0] == min(tried, key=lambda v: abs(cat.to_u(name, v) - u_test))
    h = sigs[sigs["effect"] == "hotspot"].groupby("feature")["shift_sd"].mean()
    assert h["Apeak"] > 0.3 and abs(h["H"]) < 1e-9  # the toy's hotspot signature, noise-free


def test_model_yaml_round_trip_and_checks(tmp_path):
    e = NamedEffect(name="nonlinearity", value=150.0, ci_low=120.0, ci_high=float("inf"), gap_reduction=0.2,
                    reduction_ci_low=0.1, reduction_ci_high=0.3, relative_reduction=0.8, round=1)
    p = write_model(tmp_path / "model.yaml", model_dict("named", [e], reason="r"))
    m = read_model(p)
    assert m["effects_dict"] == {"nonlinearity": 150.0} and m["effects"][0]["ci_high"] == float("inf")
    with pytest.raises(WaveforestError, match="verdict"):
        model_dict("maybe", [])
    with pytest.raises(WaveforestError, match="named effect"):
        model_dict("named", [])
    (tmp_path / "bad.yaml").write_text("verdict: named\neffects: [{name: gremlins, value: 1}]\n")
    with pytest.raises(WaveforestError, match="lacks"):
        read_model(tmp_path / "bad.yaml")


def test_cli_is_registered_and_documents_its_options():
    from waveforest.cli import cli

    r = CliRunner().invoke(cli, ["diagnose", "--help"])
    assert r.exit_code == 0, r.output
    for opt in ("--selected", "--features-real", "--calibration", "--system", "--datasets", "--targets", "--fields",
                "--out", "--config"):
        assert opt in r.output


def test_cli_missing_input_is_a_clear_error(tmp_path):
    from waveforest.cli import cli

    r = CliRunner().invoke(cli, ["diagnose", "--selected", str(tmp_path / "nope.parquet"), "--features-real",
                                 str(tmp_path / "x.parquet"), "--calibration", str(tmp_path / "c.json"),
                                 "--datasets", str(tmp_path / "d.csv"), "--out", str(tmp_path / "out")])
    assert r.exit_code != 0 and "does not exist" in r.output


def test_study_simulator_recalibrates_under_a_calibration_shaping_candidate():
    """A candidate nonlinearity or trigger_loss gets S(t) recalibrated from the target pulses
    under its value (cached); the base model keeps the calibrate stage's S(t)."""
    import math

    import numpy as np
    from reference_sensor import target_pulses
    from test_sensor_calibration import true_system

    from waveforest import config
    from waveforest.diagnose.twins import StudySimulator
    from waveforest.io.pulses import list_to_padded
    from waveforest.model.calibration_pulses import CalibrationPulses
    from waveforest.sensor import noise_stats
    from waveforest.sensor.calibration import Calibration

    table, tr = target_pulses(np.random.default_rng(3), true_system(), per_target=20, b_true=0.0, n_other=0,
                              sensor_effects={"trigger_loss": 0.2})
    x, lens = list_to_padded(table.column("samples"))
    te = np.array([v[0] for v in table.column("echo_time_ns").to_pylist()])
    hdrf = np.array([0.14, 0.21, 0.41, 0.21, 0.34, 0.45])[tr["target_index"]]
    pulses = CalibrationPulses("2010_12_1", 2010, x, lens, np.ones(len(x)), te, table.column("range_m").to_numpy(),
                               hdrf / math.pi, tr["target_index"], np.ones(len(x)), noise_stats(x, lens, 50),
                               (-15.0, 45.0))
    stage = (Calibration(pulses.system_waveform(), 10.0, 1.5), {"fwhm_ns": 6.5, "noise_mean": 10.0})
    sim = StudySimulator({}, pd.DataFrame(), {}, diagnose_settings(config.validate({})),
                         calibration_pulses={"2010_12_1": pulses})
    sim.calibrations = {"2010_12_1": stage, "2012_10_1": stage}
    assert sim.calibration("2010_12_1", {"hotspot": 1.3}) is stage
    assert sim.calibration("2012_10_1", {"trigger_loss": 0.2}) is stage  # no target pulses: as calibrated
    cal, meta = sim.calibration("2010_12_1", {"trigger_loss": 0.2, "hotspot": 1.3})
    assert cal.system.energy == pytest.approx(stage[0].system.energy / 0.8, rel=1e-9)
    assert cal.noise_mean == 10.0 and meta["fwhm_ns"] == cal.system.fwhm_ns and meta["noise_mean"] == 10.0
    assert sim.calibration("2010_12_1", {"trigger_loss": 0.2})[0] is cal


# --- the real chain (virtual campaign with hidden effects): slow ------------------------------------

SLOW_CONFIG = {
    "seed": 11,
    "data": None,
    "datasets": ["2010_12_1", "2012_10_1"],
    "campaign": {"samples_per_species": 20, "species": ["birch", "raspberry", "fireweed"], "n_rays": 2000,
                 "max_order": 5},
    "mcrt": {"n_rays": 3000, "max_order": 5},
    "select": {"min_pulses": 5},
    "simulate": {"chunks": 1},
    "sensitivity": {"pulses": 20},
    "sensor_study": {"pulses": 20},
    "diagnose": {"rounds": 2, "bootstrap": 200, "pulses_per_species": None},  # every comparison pulse, as measured below
}
"""A small study on which each hidden effect is diagnosed (the chain up to ``compare`` takes
~5 minutes on the 2-core machine; ``diagnose`` 2 minutes when nothing clears the noise floor,
13-22 minutes for a search): two datasets, the three modelled species only, 20 field samples of
each (1210 comparison pulses, all of them fitted and tested). The
campaign and the analysis trace the same orders: orders 6-10 carry ~8 % of a raspberry
canopy's sigma, a gap of its own that no catalogue effect is meant to explain. The diagnosis
figures below were measured with the earlier birch crown (base 0.3 h, longest branch 0.25 h)
and twins rendered at gain 1 with the CFD untuned (f 0.5, delay FWHM/2; birch echoes ~6 cm low),
except where said. With the present crown, twins at their real pulse's AGC gain and the CFD tuned
against the DR ranges the campaign without effects names nothing: gap 0.0238 [0.0065, 0.0561],
floor 0.0243 (seed 11; 0.0272 [0.0075, 0.0623], floor 0.0239 with the CFD untuned)."""


MORE_SAMPLES = {"campaign": {"samples_per_species": 40}}
"""Overrides for an effect whose signature is a spread between plants (clumping; also in the
two-effect campaign, which hides clumping):
the bootstrap resamples field samples, so more pulses do not add power, more samples do. With
40 (2364 comparison pulses, 240 samples; the present birch crown) clumping is named, 0.145
[0.111, 0.188] around the true 0.15, reduction 0.090 [0.061, 0.119], gap 0.127 -> 0.0135, floor
0.0142 (seed 11; 41 minutes for the whole test, diagnose 39 of them); with 20 it ranks first with
0.184 [0.089, 0.326] but its reduction 0.088 [-0.072, 0.248] is not significant. Re-measured with
the CFD tuned and armed on the recorded noise, and named effects' intervals clear of "off":
0.129 [0.105, 0.165], reduction 0.093 [0.062, 0.123], gap 0.124 -> 0.0132, floor 0.0143 (47
minutes, partly beside another run).

Also the campaign of the noise_autocorr test (measured 2026-11-27). On SLOW_CONFIG a hidden
0.7 lies at that campaign's detection limit: with the stratum near the stem it ended
unexplained (ranked first, gap 0.110 [0.0397, 0.531], floor 0.0643, "not detectable within the
bounds"); without the stratum, same inputs, none (gap 0.0548 [0.0224, 0.122], floor 0.0348,
limit 0.68). With 40 samples and the stratum (2979 pulses, 192 samples; 23.5 minutes): named,
0.778 [0.508, 0.948], test-half reduction 0.056 [0.015, 0.097], gap 0.0505 -> 0.0134, floor
0.0222, limit 0.21."""

BIRCH_ONLY = {"campaign": {"species": ["birch"], "samples_per_species": 40, "density_scale": 6.0},
              "diagnose": {"fit_pulses": 200}}
"""Overrides for an effect that only birch shows (xy_error): a campaign of birches alone, 40 per
year at six times the pulse density (2377-2380 comparison pulses, 80 samples; fits on 200
pulses per dataset). Measured (seed 11): without effects nothing is named, gap 0.0041 [-0.0002,
0.0117], floor 0.0035, birch H d +0.01, +0.03 (0.0063 [0.0020, 0.0145] with the CFD untuned,
birch H d -0.11, -0.07; 0.0158 [0.0081, 0.0267] with twins rendered at gain 1 too, most of it
birch Npeaks; 2 minutes for the whole test); a hidden xy_error 0.25 is named, 0.321 [0.215,
0.421], reduction 0.120 [0.064, 0.177], gap 0.140 -> 0.0101, floor 0.0047 (6 minutes; with the
CFD untuned 0.348 [0.167, 0.406], gap 0.139 -> 0.0196; with twins at gain 1 too: 0.301 [0.221,
0.403], gap 0.165 -> 0.0152).
On the three-species campaign its 203 birch pulses leave it unnamed.
At 80 birches per year (160 samples, 4739 pulses) nothing is named without effects either: gap
0.0076 [0.0038, 0.0140], floor 0.0016 (seed 11)."""

MORE_BIRCHES = {"campaign": {**BIRCH_ONLY["campaign"], "samples_per_species": 80}, "diagnose": BIRCH_ONLY["diagnose"]}
"""BIRCH_ONLY with 80 birches per year: the campaign of the xy_error test. BIRCH_ONLY's own
campaign has shrunk since its figures were measured (581 comparison pulses, 32 samples: only its
birches of 2.5-5 m are compared, 17 and 15 of the 40 per year), and on
it a hidden xy_error 0.25 fits 0.256 with the stratum near the stem but its reduction 0.078
[-0.018, 0.173] is not significant. With 80 (1370 pulses, 67 samples; seed 11, 8 minutes):
named, 0.215 [0.141, 0.306], test-half reduction 0.047 [0.010, 0.084], gap 0.115 -> 0.0187,
floor 0.0071. Without effects it names nothing: gap 0.0063 [0.0012, 0.018], floor 0.0047 (1900
pulses; docs/validation.md, Near the stem)."""

UNDER_CROWNS = {"campaign": BIRCH_ONLY["campaign"], "diagnose": {**BIRCH_ONLY["diagnose"], "below_crown": True}}
"""BIRCH_ONLY with the pulses under the crowns compared as a stratum of their own
(``diagnose.below_crown``: own first CFD echo within 0.5 m of the stem and lower than 1 m,
20 and 58 pulses without effects; each twin the first of up to 16 traces of its beam, turned
about the stem, that meets the same rule): the understory's signature. Paired on the same
pulses of a campaign of 80 birches per year, the understory 2.5 raises their E by 4.1 / 3.3
and Apeak by 2.5 / 3.2 pooled SDs, and the crown pulses' E by -0.02 / -0.08. Measured (seed
11): a hidden understory 2.5 is named, 2.66 [2.20, 2.90], reduction 4.28 [2.01, 6.55], no
look-alike, gap 5.46 -> 0.0602, floor 0.115 (diagnose 18 minutes beside another run); without
effects nothing is named, gap 0.0682 [0.0053, 0.259], floor 0.0591. (With one trace per pulse
and the real side drawn by the DR echo, only 4-17 twins per dataset stayed under the crowns:
2.54 [1.52, 2.67], floor 0.207; without effects floor 0.125.) With a hidden
xy_error 0.25 the search still ends unexplained: xy_error fits 0.385 [0.300, 0.446], reduction
1.01 [-0.14, 2.16] (0.50 and 0.70 [-0.13, 1.52] before); under the crowns the twins still want
a larger error than the campaign's. So xy_error keeps a campaign of birches alone without
the stratum (MORE_BIRCHES), and ``below_crown`` is off by default."""

OVERRIDES = {"clumping": MORE_SAMPLES, "xy_error": MORE_BIRCHES, "understory": UNDER_CROWNS,
             "noise_autocorr": MORE_SAMPLES}
"""The campaign (and diagnose settings) of each effect's test, where SLOW_CONFIG's is too small."""


def _diagnose_campaign(tmp_path, effects: dict, overrides: dict | None = None) -> dict:
    """Run the workflow up to ``diagnose`` on a virtual campaign with ``effects`` hidden in it
    (``overrides``: config section -> keys replacing SLOW_CONFIG's)."""
    if shutil.which("snakemake") is None:
        pytest.skip("snakemake not installed")
    for name in ("Snakefile", "workflow", "config"):
        src = ROOT / name
        (shutil.copytree(src, tmp_path / name, symlinks=False) if src.is_dir()
         else shutil.copy(src, tmp_path / name))
    cfg = yaml.safe_load(yaml.safe_dump(SLOW_CONFIG))
    for section, keys in (overrides or {}).items():
        cfg[section].update(keys)
    cfg["campaign"]["effects"] = effects
    (tmp_path / "config" / "slow.yaml").write_text(yaml.safe_dump(cfg))
    # the target goes first: Snakemake's --configfile takes every value that follows it
    subprocess.run([sys.executable, "-m", "snakemake", "results/diagnose/model.yaml", "--cores", "2",
                    "--configfile", "config/slow.yaml"], cwd=tmp_path, check=True, capture_output=True)
    return read_model(tmp_path / "results" / "diagnose" / "model.yaml")


@pytest.mark.slow
@pytest.mark.parametrize("overrides", [None, BIRCH_ONLY, MORE_BIRCHES, UNDER_CROWNS],
                         ids=["three_species", "birch_only", "more_birches", "under_crowns"])
def test_real_chain_no_effect_names_nothing(tmp_path, overrides):
    m = _diagnose_campaign(tmp_path, {}, overrides)
    assert m["effects"] == [] and m["verdict"] in ("none", "unexplained")


# The stratum near the stem and SLOW_CONFIG (2026-11-27): its birches (5-8 field samples per
# dataset) are too few for the split (strata.NEAR_STEM_MIN_SAMPLES), so its campaigns are
# diagnosed with one cell per species. Split all the same, as before that rule, small cells gave
# the bootstrap a long tail: a hidden trigger_loss 0.15 ended in none (gap 0.113 [0.0274, 0.422],
# floor 0.0908) and a LAD shift of 15 deg unexplained (fitted 13.5, reduction 0.563 [-0.372,
# 1.5], gap 0.695 [0.531, 1.6], floor 0.0731). With one cell, on the same inputs: trigger_loss
# named 0.144 [0.116, 0.218], gap 0.0727 -> 0.0246, floor 0.0472 (10 min); lad_shift named 14.0
# [13.3, 18.5], reduction 0.590 [0.427, 0.752], gap 0.573 -> 0.0308, floor 0.0410 (12 min).
# ``noise_autocorr`` and ``trigger_loss`` pass since the fits and tests use all comparison
# pulses (``diagnose.fit_pulses`` null; seed 11):
# noise_autocorr 0.666 [0.424, 0.793] around 0.7, gap 0.0355 -> 0.021, floor 0.0251 (not named
# with fits on 40 pulses per dataset x species: 0.91 [0.46, 0.95]); trigger_loss 0.143 [0.112,
# 0.202] around 0.15, gap 0.069 -> 0.0345, floor 0.0266. ``nonlinearity`` passes since S(t) is
# recalibrated under each value tried (:mod:`waveforest.diagnose.twins`), the saturation acts
# after the AGC gain and each fit takes 3 refinement steps: 152 [144, 172] around 150, gap 0.417
# -> 0.048, floor 0.071 (fits and tests on 240 pulses).
# Re-measured with twins at their pulse's AGC gain and the CFD tuned against the DR ranges:
# noise_autocorr 0.608 [0.413, 0.796], reduction 0.026 [0.009, 0.042], gap 0.0435 -> 0.0188,
# floor 0.0236 (15 minutes; the CFD arming on the recorded noise, SD / gain, is what keeps
# twins at low gain from firing on correlated noise: armed at 4 SD of the normalised noise the
# "after" gap rose to 0.0573); trigger_loss 0.191 [0.131, 0.230], reduction 0.078 [0.044, 0.111],
# gap 0.0935 -> 0.0311, floor 0.024 (15 minutes); hotspot 1.313 [1.283, 1.340] around 1.3,
# gap 0.944 -> 0.0306, floor 0.035 (15 minutes); with that change too: nonlinearity 152.4 [147.9,
# 159.0], gap 0.308 -> 0.0237, floor 0.0281 (15 minutes; before it, the same interval), and
# (each 24-29 minutes beside another run) specular 0.320 [0.296, 0.347] around 0.3, gap 0.618
# -> 0.0299, floor 0.0341; leaf_albedo 0.852 [0.848, 0.858] around 0.85, gap 1.81 -> 0.022, floor
# 0.0445; lad_shift 15.05 [12.44, 15.98] around 15, gap 0.540 -> 0.0196, floor 0.0321.


UNDERSTORY_NOT_NAMED = pytest.mark.xfail(strict=True, reason=(
    "issue 28: on UNDER_CROWNS' campaign as it is now (803 pulses with those under the crowns, 32 "
    "samples; 80 samples when the figures above were measured) a hidden understory 2.5 ends in none: "
    "gap 3.82 [2.63, 207], floor 0.143, the stratum's few pulses giving the bootstrap a huge tail; the "
    "same without the stratum near the stem (5.72 [3.94, 310], floor 0.208); docs/validation.md, Near "
    "the stem"))


@pytest.mark.slow
@pytest.mark.parametrize("name", [pytest.param(n, marks=UNDERSTORY_NOT_NAMED) if n == "understory" else n
                                  for n in CATALOGUE])
def test_real_chain_names_the_hidden_effect(tmp_path, name):
    truth = CATALOGUE[name].test_value
    m = _diagnose_campaign(tmp_path, {name: truth}, OVERRIDES.get(name))
    assert m["verdict"] == "named"
    first = m["effects"][0]
    assert first["name"] == name
    assert first["ci_low"] <= truth <= first["ci_high"]
    gap = m["gap"]  # the excess over the noise floor (a perfect model's gap) at least halves
    assert gap["after"] - gap["noise_floor"] <= 0.5 * (gap["before"] - gap["noise_floor"])


@pytest.mark.slow
def test_real_chain_two_effects_over_two_rounds(tmp_path):
    """Hotspot and clumping at once, with clumping's 40 field samples (MORE_SAMPLES). Measured
    with the present birch crown, the CFD tuned and armed on the recorded noise (seed 11; 131
    minutes beside other runs, diagnose 129 of them, 400 simulations): hotspot named in round 1
    (reduction 0.408 [0.336, 0.481]), clumping in round 2 (0.081 [0.053, 0.108]); after the
    re-fit hotspot 1.31 [1.29, 1.33] around 1.3, clumping 0.121 [0.097, 0.157] around 0.15; gap
    0.511 -> 0.0109, noise floor 0.017. With 20 samples clumping ranked first in round 2 (0.203
    [0.141, 0.754]) but its reduction 0.038 [-0.023, 0.100] was not significant, as alone."""
    truth = {"hotspot": 1.3, "clumping": 0.15}  # one in the scattering, one in the plants
    m = _diagnose_campaign(tmp_path, truth, MORE_SAMPLES)
    assert {e["name"] for e in m["effects"]} == set(truth)
    assert sorted(e["round"] for e in m["effects"]) == [1, 2]
    assert all(e["ci_low"] <= truth[e["name"]] <= e["ci_high"] for e in m["effects"])
    gap = m["gap"]
    assert gap["after"] - gap["noise_floor"] <= 0.5 * (gap["before"] - gap["noise_floor"])


def test_scene_cache_keeps_base_plants_at_once_and_candidate_plants_from_their_second_request():
    """A candidate's vegetation value is mostly simulated once: its plants must not push the
    base model's plants (traced again by every other candidate) out of the cache."""
    from waveforest.diagnose.twins import SceneCache

    cache = SceneCache(base_effects={"hotspot": 1.3})  # no vegetation effect in the base model
    kw = dict(ground_rho=0.3, lai_jitter=0.1)
    a = cache("birch", 1.2, 7, **kw)
    assert cache("birch", 1.2, 7, **kw, leaf_albedo=1.0) is a  # an off value is the base plant
    assert (cache.built, cache.hits) == (1, 1)
    b = cache("birch", 1.2, 7, **kw, leaf_albedo=0.8)
    assert b is not a and len(cache.scenes) == 1  # built, not kept
    c = cache("birch", 1.2, 7, **kw, leaf_albedo=0.8)
    assert cache.built == 3 and len(cache.scenes) == 2 and cache("birch", 1.2, 7, **kw, leaf_albedo=0.8) is c
    np.testing.assert_array_equal(b.scene.triangles, c.scene.triangles)  # the same plant either way
    assert not np.array_equal(a.tri_data[:, 3], b.tri_data[:, 3])  # leaf albedo scales rho
    assert b.intersector is a.intersector  # optics only: the base plant's BVH


def test_scene_cache_smaller_than_a_simulations_plants_keeps_serving_part_of_them():
    """Plants requested in the same order by every simulation (a pass): with room for 3 of 5, a
    least-recently-used cache would miss every request; this one keeps 3 for the next pass and
    drops them for a pass over other plants."""
    from waveforest.diagnose.twins import SceneCache

    cache = SceneCache(size=3)
    for _ in range(3):
        cache.new_pass()
        for seed in range(5):
            cache("birch", 1.2, seed)
    assert (cache.built, cache.hits) == (5 + 2 * 2, 2 * 3) and len(cache.scenes) == 3
    cache.new_pass()
    for seed in (11, 12, 13):  # another model's plants: the previous pass's make room
        cache("birch", 1.2, seed)
    cache.new_pass()
    for seed in (11, 12, 13):
        cache("birch", 1.2, seed)
    assert cache.hits == 2 * 3 + 3 and {k[2] for k in cache.scenes} == {11, 12, 13}


def test_trace_cache_returns_the_trace_of_the_same_scene_beams_seed_and_keywords():
    """A cached trace is the trace; another seed, keyword, beam or scene object traces anew;
    an entry ends with its scene; the cache keeps within its bytes."""
    import gc

    from fixtures import scenes as syn

    from waveforest.diagnose.twins import TraceCache, sigma_effects
    from waveforest.mcrt import Beams, prepare, trace

    scene = prepare(syn.sheet_over_ground(6.0, 0.3))
    beams = Beams.toward(np.zeros((2, 3)), 1000.0, [0.0, 8.0], [0.0, 90.0], divergence_mrad=0.15)
    kw = dict(n_rays=256, max_order=3, sampler="sobol", roulette=0.5)
    cache = TraceCache()
    first = cache(scene, beams, seed=3, threads=1, **kw)
    np.testing.assert_array_equal(first.sigma, trace(scene, beams, seed=3, **kw).sigma)
    assert cache(scene, beams, seed=3, threads=2, **kw) is first and cache.hits == 1  # threads change nothing
    assert cache(scene, beams, seed=4, **kw) is not first
    assert cache(scene, beams, seed=3, **{**kw, "hotspot": 1.2}) is not first
    moved = Beams.toward(np.full((2, 3), 0.01), 1000.0, [0.0, 8.0], [0.0, 90.0], divergence_mrad=0.15)
    assert cache(scene, moved, seed=3, **kw) is not first
    other = prepare(syn.sheet_over_ground(6.0, 0.3))
    assert cache(other, beams, seed=3, **kw) is not first and cache.hits == 1
    assert len(cache.entries) == 5 and cache.bytes == 5 * first.sigma.nbytes
    del other
    gc.collect()
    stale = [k for k, (ref, _) in cache.entries.items() if ref() is None]
    assert len(stale) == 1  # its scene is gone: the entry can no longer be hit
    small = TraceCache(max_bytes=2 * first.sigma.nbytes)
    for seed in range(4):
        small(scene, beams, seed=seed, **kw)
    assert len(small.entries) == 2 and small.bytes <= small.max_bytes
    # the models that trace the base model's sigma(t): sensor effects only, off values aside
    assert sigma_effects({"nonlinearity": 300.0, "trigger_loss": 0.1}) == sigma_effects({})
    assert sigma_effects({"specular": 0.0}) == () != sigma_effects({"specular": 0.1})
    assert sigma_effects({"xy_error": 0.2}) != sigma_effects({}) != sigma_effects({"leaf_albedo": 0.9})
