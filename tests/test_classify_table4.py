"""classify, the Table 4 analogue as the paper has it (docs/method.md §(i4)): Table 1's species
rule across datasets, the + max H extra, a known-answer LDA, and reasons beside null cells."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from waveforest import config
from waveforest.analysis.classify import add_sample_features, classify_dataset, species_table
from waveforest.cli import main
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.settings import classify_settings
from waveforest.stages.classify import run
from waveforest.stats import lda

CENTRES = {"conifer": (0.5, 0.4), "broadleaf": (0.7, 0.6), "low_green": (1.2, 1.3),
           "low_barren_abiotic": (0.4, 1.1)}


def _pulses(dataset, spec, rng, *, sand=12, spread=0.02):
    """Selected real pulses of one dataset with features.

    spec: {species: (functional group, samples, single-echo pulses per sample)}; every sample
    also has one two-echo pulse (never classified). E and Apeak sit near the group's centre
    (times 1500 and 100); H of pulse k of a sample is 0.1 k m.
    """
    rows = []
    for sp, (group, n_samples, per_sample) in spec.items():
        for s in range(n_samples):
            for k in range(per_sample + 1):
                e, a = (np.array(CENTRES[group]) + rng.normal(0, spread, 2)) * [1500, 100]
                rows.append(dict(dataset=dataset, source="real", sample_id=f"{dataset}-{sp}-{s}", species=sp,
                                 functional_group=group, n_echoes=1 if k < per_sample else 2,
                                 E=e, Apeak=a, FWHM=rng.normal(10, 1), H=0.1 * k))
    for i in range(sand):
        rows.append(dict(dataset=dataset, source="real", sample_id=f"{dataset}-sand-{i % 3}", species="sand_road",
                         functional_group="low_barren_abiotic", n_echoes=1, E=2000.0, Apeak=150.0,
                         FWHM=8.0, H=0.0))
    df = pd.DataFrame(rows)
    df.insert(1, "pulse_id", np.arange(len(df)))
    df["single_echo_set"] = df["n_echoes"] == 1
    return df


# Table 1's rule, the brief's case: pine 35 + 10 single-echo pulses (A, B) is in both datasets'
# classification sets, birch 20 + 20 in none; raspberry and heather (40 each) pass everywhere.
SPEC_A = {"scots_pine": ("conifer", 5, 7), "birch": ("broadleaf", 4, 5), "raspberry": ("low_green", 5, 8),
          "heather": ("low_barren_abiotic", 5, 8)}
SPEC_B = {"scots_pine": ("conifer", 2, 5), "birch": ("broadleaf", 4, 5), "raspberry": ("low_green", 5, 8),
          "heather": ("low_barren_abiotic", 5, 8)}


def _two_datasets():
    rng = np.random.default_rng(11)
    return _pulses("A", SPEC_A, rng), _pulses("B", SPEC_B, rng)


def test_species_rule_counts_over_every_dataset():
    a, b = _two_datasets()
    t = species_table(pd.concat([a, b]), 30).set_index("species")
    assert t.loc["scots_pine", ["A", "B"]].tolist() == [35, 10]
    assert t.loc["birch", ["A", "B"]].tolist() == [20, 20]
    assert t.loc["scots_pine", "included"] and not t.loc["birch", "included"]
    assert t.loc["sand_road", "functional_group"] == "low_barren_abiotic"

    cfg = config.load()  # min_pulses 30
    for df, n_pine in ((a, 35), (b, 10)):
        r = classify_dataset(df, classify_settings(cfg), selection=pd.concat([a, b]))
        assert r["species"] == {"heather": 40, "raspberry": 40, "scots_pine": n_pine}
        assert r["pulses_per_group"] == {"conifer": n_pine, "broadleaf": 0, "low_green": 40,
                                         "low_barren_abiotic": 40}
        assert r["main"]["groups_missing"] == ["broadleaf"]
        assert r["main"]["one_pulse"]["resubstitution"]["accuracy"] == 1.0
        rows = {row["species"]: row for row in r["species_table"]}
        assert rows["scots_pine"]["pulses"] == {"A": 35, "B": 10} and rows["scots_pine"]["included"]
        assert rows["birch"]["pulses"] == {"A": 20, "B": 20} and not rows["birch"]["included"]
        assert r["species_rule"]["datasets"] == ["A", "B"]
    # without the other dataset, B's 10 pine pulses fall under the rule (counted within B)
    alone = classify_dataset(b, classify_settings(cfg))
    assert "scots_pine" not in alone["species"] and alone["pulses_per_group"]["conifer"] == 0
    assert alone["species_rule"]["datasets"] == ["B"]


def test_cli_reads_every_select_table(tmp_path):
    a, b = _two_datasets()
    paths = {}
    for name, df in (("A", a), ("B", b)):
        paths[name] = tmp_path / f"{name}_select.parquet"
        df.drop(columns=["E", "Apeak", "FWHM", "H"]).to_parquet(paths[name])
        # the feature table lacks select's flag: the join on (dataset, pulse_id) adds it
        df.drop(columns=["single_echo_set"]).to_parquet(tmp_path / f"{name}_real.parquet")
    main(["classify", str(tmp_path / "B_real.parquet"), "--select", str(paths["A"]), str(paths["B"]),
          "--out", str(tmp_path / "B.json")])
    text = (tmp_path / "B.json").read_text()
    assert "NaN" not in text
    r = json.loads(text)
    assert r["species"]["scots_pine"] == 10 and "birch" not in r["species"]
    assert r["species_rule"]["min_pulses"] == 30
    with pytest.raises(WaveforestError, match="none of the select tables"):
        run(tmp_path / "B_real.parquet", tmp_path / "x.json", config.load(), select_paths=[paths["A"]])


def test_counts_are_those_of_the_pulses_the_accuracy_was_computed_on(tmp_path, capsys):
    """Pulses without E or Apeak (no first-echo segment) leave the LDA: n_pulses, the per-group
    counts and the confusion matrix agree, and the JSON says how many left and why."""
    a, _ = _two_datasets()
    a["Npeaks"] = 1
    lost = a.index[(a["species"] == "raspberry") & a["single_echo_set"]][:3]
    a.loc[lost, ["E", "Apeak", "Npeaks"]] = [np.nan, np.nan, 0]
    a.loc[lost[2], "Npeaks"] = 1  # one without a first echo's segment is not the rule for all
    r = classify_dataset(a, classify_settings(config.load()))
    confusion = np.sum(r["main"]["one_pulse"]["resubstitution"]["confusion"])
    assert r["n_pulses"] == r["main"]["n_pulses"] == confusion == 35 + 40 + 40 - 3
    assert r["pulses_per_group"]["low_green"] == r["species"]["raspberry"] == 37
    assert r["pulses_per_sample"] == pytest.approx(confusion / r["n_samples"])
    assert r["main"]["n_dropped"] == 3 and r["main"]["dropped_reason"] == "no value of E or Apeak"
    fwhm_only = [e for e in r["extra"] if e["features"] == ["E", "Apeak", "FWHM"]][0]
    assert fwhm_only["n_dropped"] == 3
    a.loc[lost[2], "Npeaks"] = 0
    a.to_parquet(tmp_path / "A_real.parquet")
    main(["classify", str(tmp_path / "A_real.parquet"), "--out", str(tmp_path / "A.json")])
    assert ("classify: A: 3 pulse(s) left out, no value of E or Apeak: no first-echo segment above the noise "
            "threshold, Npeaks 0") in capsys.readouterr().out
    assert json.loads((tmp_path / "A.json").read_text())["n_pulses"] == 112


def test_max_h_is_the_sample_maximum_and_not_normalised():
    df = pd.DataFrame(dict(sample_id=["s1", "s1", "s1", "s2", "s2"], H=[0.2, np.nan, 0.9, 0.4, 0.1]))
    assert add_sample_features(df)["maxH"].tolist() == [0.9, 0.9, 0.9, 0.4, 0.4]
    # groups that differ only by the height of their samples: E and Apeak cannot tell them
    # apart, maxH (the sample's tallest pulse, 0.1 (n - 1) m) separates them exactly
    rng = np.random.default_rng(12)
    spec = {"raspberry": ("low_green", 6, 12), "heather": ("low_barren_abiotic", 6, 4)}
    df = _pulses("A", spec, rng, spread=0.3)
    df[["E", "Apeak"]] = rng.normal(1000, 100, (len(df), 2))
    df["H"] += rng.uniform(0, 0.05, len(df))
    cfg = config.load(overrides={"select": {"min_pulses": 5},
                                 "classify": {"extra_feature_sets": [["maxH"], ["E", "Apeak", "maxH"]]}})
    r = classify_dataset(df, classify_settings(cfg))
    assert set(r["normaliser"]) == {"species", "n", "E", "Apeak", "FWHM"}  # no height is divided
    only_h, with_h = r["extra"]
    for level in ("one_pulse", "mean_of_sample"):
        for scheme in ("resubstitution", "cross_validated"):
            assert only_h[level][scheme]["accuracy"] == 1.0
            assert with_h[level][scheme]["accuracy"] == 1.0
    assert only_h["mean_of_sample"]["resubstitution"]["n"] == 12  # one mean per sample
    assert r["main"]["one_pulse"]["cross_validated"]["accuracy"] < 0.9
    main_cv = r["main"]["one_pulse"]["cross_validated"]["accuracy"]
    assert only_h["gain_pp"]["one_pulse"]["cross_validated"] == pytest.approx(100 * (1 - main_cv))


def test_lda_known_answer_with_class_frequency_priors():
    """1-D, classes a = {0, 3.05}, b = {3, 5, 7}: pooled variance (within-class sum of squares
    over n, scikit-learn's) 12.651 / 5 = 2.530; boundary (mu_a + mu_b) / 2 + s2 ln(p_a / p_b) /
    (mu_b - mu_a) = 3.2625 - 0.2952 = 2.967 with priors 2/5, 3/5: a's 3.05 goes to b, b's 3 stays
    (equal priors would put the boundary at 3.2625 and send b's 3 to a instead)."""
    x = np.array([0.0, 3.05, 3.0, 5.0, 7.0]).reshape(-1, 1)
    y = np.array(["a", "a", "b", "b", "b"], dtype=object)
    s = lda.scores(y, lda.resubstitution(x, y), ["a", "b"])
    assert s.confusion.tolist() == [[1, 1], [0, 3]]
    assert s.accuracy == pytest.approx(0.8)
    # p_o = 0.8, p_e = (2 * 1 + 3 * 4) / 25 = 0.56: kappa = 0.24 / 0.44
    assert s.kappa == pytest.approx(0.24 / 0.44)


def test_lda_without_spread_within_classes():
    """One value per class (a sample-level feature): the class means classify exactly."""
    x = np.array([[1.0], [1.0], [2.0], [2.0], [4.0]])
    y = np.array(["a", "a", "b", "b", "c"], dtype=object)
    assert lda.resubstitution(x, y).tolist() == y.tolist()


def test_lda_matches_the_discriminant_formula():
    """Predictions equal argmax_k x S^-1 mu_k - mu_k S^-1 mu_k / 2 + ln p_k (S pooled, over n)."""
    rng = np.random.default_rng(13)
    n = np.array([40, 70, 25])
    means = np.array([[0.0, 0.0], [1.0, 0.5], [0.3, 1.2]])
    x = np.concatenate([rng.multivariate_normal(m, [[1, 0.4], [0.4, 0.8]], k) for m, k in zip(means, n)])
    y = np.repeat(np.array(["p", "q", "r"], dtype=object), n)
    mu = np.array([x[y == c].mean(axis=0) for c in "pqr"])
    resid = x - mu[np.searchsorted(np.array(list("pqr")), y.astype(str))]
    inv = np.linalg.inv(resid.T @ resid / len(x))
    delta = x @ inv @ mu.T - 0.5 * np.einsum("kf,fg,kg->k", mu, inv, mu) + np.log(n / n.sum())
    expected = np.array(list("pqr"), dtype=object)[np.argmax(delta, axis=1)]
    assert np.array_equal(lda.resubstitution(x, y), expected)


def test_degenerate_input_says_why():
    rng = np.random.default_rng(14)
    cfg = config.load(overrides={"select": {"min_pulses": 5}})
    one = _pulses("A", {"scots_pine": ("conifer", 3, 6), "birch": ("broadleaf", 1, 2)}, rng)
    r = classify_dataset(one, classify_settings(cfg))
    assert r["main"]["one_pulse"] is None and r["main"]["mean_of_sample"] is None
    assert "only conifer" in r["main"]["reason"] and "broadleaf" in r["main"]["reason"]
    assert r["main"]["groups_missing"] == ["broadleaf", "low_green", "low_barren_abiotic"]
    assert r["pulses_per_group"] == {"conifer": 18, "broadleaf": 0, "low_green": 0, "low_barren_abiotic": 0}
    assert all(e["reason"] and e["one_pulse"] is None for e in r["extra"])
    assert r["extra"][0]["gain_pp"]["mean_of_sample"]["resubstitution"] is None
    ts = r["three_species"]
    assert ts["one_pulse"] is None and "0 pulses: birch, raspberry, fireweed" in ts["reason"]
    # nothing passes the rule
    none = classify_dataset(one, classify_settings(config.load()))
    assert none["n_pulses"] == 0 and "none has any" in none["main"]["reason"]
    # two groups of one pulse each: LDA runs, cross-validation cannot
    two = _pulses("A", {"scots_pine": ("conifer", 1, 1), "raspberry": ("low_green", 1, 1)}, rng, sand=0)
    with pytest.warns(WaveforestWarning, match="not normalised"):
        r2 = classify_dataset(two, classify_settings(config.load(overrides={"select": {"min_pulses": 1}})))
    assert "features are not normalised" in r2["normaliser"]["reason"]
    level = r2["main"]["one_pulse"]
    assert level["resubstitution"]["n"] == 2 and level["cross_validated"] is None
    assert "fewer than 2 folds" in level["cross_validated_reason"]
    assert r2["main"]["reason"] is None and level["resubstitution"]["accuracy"] == 1.0
    # a five-pulse mean needs five pulses of one sample
    few = _pulses("A", {"birch": ("broadleaf", 3, 3), "raspberry": ("low_green", 3, 6)}, rng)
    ts = classify_dataset(few, classify_settings(config.load(overrides={"select": {"min_pulses": 2}})))["three_species"]
    assert ts["one_pulse"] is not None and ts["multi_pulse"] is None
    assert "only raspberry" in ts["multi_pulse_reason"]


def test_later_echo_amplitude_is_normalised_by_the_road_apeak():
    """The road's single-echo pulses have no later echoes (gd_later_A 0): a normaliser mean of 0
    must not stop the study; gd_later_A is divided by the road's mean Apeak (the same DN scale)."""
    from waveforest.analysis.classify import normalise

    df = pd.DataFrame(dict(species=["sand_road"] * 3 + ["birch"] * 2, Apeak=[50.0, 60.0, 70.0, 30.0, 40.0],
                           gd_later_A=[0.0, 0.0, 0.0, 12.0, 24.0], E=[1.0, 2.0, 3.0, 4.0, 5.0]))
    out, record = normalise(df, ["Apeak", "gd_later_A", "E"], "sand_road")
    assert record["gd_later_A"] == pytest.approx(60.0) and record["Apeak"] == pytest.approx(60.0)
    assert out["gd_later_A"].tolist() == pytest.approx([0, 0, 0, 0.2, 0.4])
    assert out["E"].tolist() == pytest.approx([0.5, 1.0, 1.5, 2.0, 2.5])
    df.loc[:2, "Apeak"] = 0.0
    with pytest.raises(WaveforestError, match="mean Apeak is 0.0; cannot normalise"):
        normalise(df, ["gd_later_A"], "sand_road")
