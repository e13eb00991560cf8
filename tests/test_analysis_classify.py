"""classify and lda: known answers on synthetic separable / non-separable data (docs/method.md §(i4))."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from sklearn.metrics import cohen_kappa_score
from sklearn.metrics import confusion_matrix as sk_confusion

from waveforest import config
from waveforest.analysis.classify import classification_rows, classify_dataset
from waveforest.cli import main
from waveforest.io.paper import table4 as paper_table4
from waveforest.report.build import table4
from waveforest.settings import classify_settings
from waveforest.stats import lda

GROUPS = ["conifer", "broadleaf", "low_green", "low_barren_abiotic"]
SPECIES = {"conifer": "scots_pine", "broadleaf": "birch", "low_green": "raspberry",
           "low_barren_abiotic": "heather"}


def _features(rng, separable=True, samples_per_group=6, pulses_per_sample=8, sand=20):
    """A feature table: four groups (plus a sand road), several samples each."""
    rows = []
    centres = {"conifer": (0.5, 0.4), "broadleaf": (0.7, 0.6), "low_green": (1.2, 1.3),
               "low_barren_abiotic": (0.4, 1.1)}
    pid = 0
    for g in GROUPS:
        for s in range(samples_per_group):
            for _ in range(pulses_per_sample):
                c = centres[g] if separable else (0.8, 0.8)
                e, a = (np.array(c) + rng.normal(0, 0.02 if separable else 0.2, 2)) * np.array([1500, 100])
                rows.append(dict(dataset="d1", pulse_id=pid, source="real", sample_id=f"{g}-{s}",
                                 species=SPECIES[g], functional_group=g, n_echoes=1,
                                 E=e, Apeak=a, FWHM=rng.normal(10, 1), H=0.5))
                pid += 1
    for i in range(sand):
        rows.append(dict(dataset="d1", pulse_id=pid, source="real", sample_id=f"sand-{i % 3}",
                         species="sand_road", functional_group="low_barren_abiotic", n_echoes=1,
                         E=2000.0 + 10 * (i % 2), Apeak=150.0, FWHM=8.0, H=0.0))
        pid += 1
    return pd.DataFrame(rows)


def test_kappa_matches_sklearn():
    rng = np.random.default_rng(1)
    labels = ["a", "b", "c"]
    for _ in range(20):
        t = rng.choice(labels, 200)
        p = np.where(rng.random(200) < 0.6, t, rng.choice(labels, 200))
        s = lda.scores(t, p, labels)
        assert s.kappa == pytest.approx(cohen_kappa_score(t, p), abs=1e-12)
        assert np.array_equal(s.confusion, sk_confusion(t, p, labels=labels))
        assert s.accuracy == pytest.approx(np.mean(t == p))
    # analytic: 2x2 with po = 0.7, pe = 0.5 -> kappa 0.4
    assert lda.cohen_kappa(np.array([[35, 15], [15, 35]])) == pytest.approx(0.4)


def test_separable_groups_are_classified_perfectly():
    rng = np.random.default_rng(2)
    df = _features(rng)
    cfg = config.load(overrides={"select": {"min_pulses": 5}})
    r = classify_dataset(df, classify_settings(cfg))
    for level in ("one_pulse", "mean_of_sample"):
        for scheme in ("resubstitution", "cross_validated"):
            assert r["main"][level][scheme]["accuracy"] == 1.0
            assert r["main"][level][scheme]["kappa"] == pytest.approx(1.0)
    assert r["n_pulses"] == 4 * 6 * 8  # sand road is only the normaliser
    assert r["normaliser"]["E"] == pytest.approx(2005.0) and r["normaliser"]["Apeak"] == pytest.approx(150.0)
    assert r["main"]["mean_of_sample"]["resubstitution"]["n"] == 24
    assert r["pulses_per_sample"] == pytest.approx(8.0)
    cm = np.array(r["main"]["one_pulse"]["resubstitution"]["confusion"])
    assert np.array_equal(np.diag(cm), [48] * 4) and cm.sum() == 192


def test_non_separable_groups_are_at_chance_when_cross_validated():
    rng = np.random.default_rng(3)
    df = _features(rng, separable=False, samples_per_group=10, pulses_per_sample=10)
    cfg = config.load(overrides={"select": {"min_pulses": 5}})
    r = classify_dataset(df, classify_settings(cfg))
    cv = r["main"]["one_pulse"]["cross_validated"]
    assert cv["accuracy"] < 0.45 and abs(cv["kappa"]) < 0.2
    # resubstitution is optimistic, never below cross-validation here by much
    assert r["main"]["one_pulse"]["resubstitution"]["accuracy"] >= cv["accuracy"] - 0.05


def test_folds_never_split_a_group():
    rng = np.random.default_rng(4)
    y = rng.choice(["a", "b", "c"], 300)
    groups = rng.integers(0, 40, 300)
    folds = lda.cv_folds(y, groups, 5, seed=0)
    assert len(folds) == 5
    seen = np.zeros(300, int)
    for train, test in folds:
        assert not set(groups[train]) & set(groups[test])
        seen[test] += 1
    assert np.all(seen == 1)
    assert lda.cv_folds(y, np.zeros(300), 5, 0) == []
    # the same labels, groups and seed: the same folds (kept from the first call), other seeds others
    lda._FOLDS.clear()
    again = lda.cv_folds(y.tolist(), groups.astype(str), 5, seed=0)
    assert len(lda._FOLDS) == 1 and lda.cv_folds(y, groups, 5, seed=0) is not again
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(folds, again))
    again[0][1][:] = -1  # a caller's change does not reach the kept folds
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(folds, lda.cv_folds(y, groups, 5, seed=0)))
    assert not all(np.array_equal(a[1], b[1]) for a, b in zip(folds, lda.cv_folds(y, groups, 5, seed=1)))


def test_consecutive_means():
    x = np.arange(12, dtype=float).reshape(-1, 1)
    y = np.array(["a"] * 7 + ["b"] * 5, dtype=object)
    units = np.array(["u1"] * 7 + ["u2"] * 5, dtype=object)
    means, labels, out_units = lda.consecutive_means(x, y, np.arange(12)[::-1], units, 3)
    # u1 sorted by order key descending rows: 6,5,4 | 3,2,1 | (0 dropped); u2: 11,10,9 | (8,7 dropped)
    got = sorted(zip(out_units, means[:, 0], labels))
    assert got == [("u1", 2.0, "a"), ("u1", 5.0, "a"), ("u2", 10.0, "b")]


def test_classification_set_rule_without_flag():
    df = pd.DataFrame(dict(species=["a"] * 3 + ["b"] * 2 + ["a"], n_echoes=[1, 1, 1, 1, 1, 2]))
    assert classification_rows(df, 3).index.tolist() == [0, 1, 2]
    df["classification_set"] = [True, False, True, True, False, False]
    assert classification_rows(df, 3).index.tolist() == [0, 2, 3]


def test_run_cli_and_table4(tmp_path):
    rng = np.random.default_rng(5)
    df = _features(rng)
    path = tmp_path / "f.parquet"
    df.to_parquet(path)
    cfgp = tmp_path / "c.yaml"
    cfgp.write_text("select:\n  min_pulses: 5\n")
    main(["classify", str(path), "--out", str(tmp_path / "d1.json"), "--config", str(cfgp)])
    text = (tmp_path / "d1.json").read_text()
    assert "NaN" not in text
    r = json.loads(text)
    assert r["dataset"] == "d1" and r["main"]["one_pulse"]["resubstitution"]["accuracy"] == 1.0
    assert r["three_species"]["species"] == ["birch", "raspberry"]
    r2 = dict(r, dataset="2010_12_1")
    t = table4([r2], paper_table4())
    assert t.loc[0, "one_pulse_correct_pct"] == pytest.approx(100.0)
    assert t.loc[0, "paper_one_pulse_correct_pct"] == pytest.approx(68.1)
    assert t.loc[0, "cv_mean_of_sample_kappa"] == pytest.approx(1.0)


def test_json_has_no_nan(tmp_path):
    from waveforest.atomic import write_json

    write_json({"a": float("nan"), "b": [np.float64(1.5), np.inf], "c": np.int64(3)}, tmp_path / "x.json")
    assert json.loads((tmp_path / "x.json").read_text()) == {"a": None, "b": [1.5, None], "c": 3}


def test_cv_with_tiny_classes():
    y = np.array(["a", "a", "b", "c"], dtype=object)
    folds = lda.cv_folds(y, np.arange(4), 5, seed=0)
    assert len(folds) == 2  # the largest class has 2 members
    pred = lda.cross_validated(np.arange(4.0).reshape(-1, 1), y, np.arange(4), 5, 0)
    assert pred is not None and len(pred) == 4
    assert lda.cv_folds(np.array(["a", "b"], dtype=object), np.arange(2), 5, 0) == []
