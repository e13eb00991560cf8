"""The signature test (waveforest.diagnose.signature_test) on synthetic clustered features."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from fixtures.study import SyntheticStudy

from waveforest.diagnose import catalogue as cat
from waveforest.diagnose.gap import ALL_FEATURES, gap_report, sample_universe
from waveforest.diagnose.power import PowerSettings, detection_limits
from waveforest.diagnose.search import SearchSettings
from waveforest.diagnose.signature_test import ALPHA, SignatureTest, critical_value, terms
from waveforest.stats.bootstrap import bootstrap_weights, cluster_df

SPECIES = ("pine", "spruce", "birch")
KW = {"min_pulses": 10, "min_samples": 2}


def _table(rng, shift: dict | None = None, samples: int = 20, pulses: int = 8, rho: float = 0.0) -> pd.DataFrame:
    """Two datasets x three species x ``samples`` field samples x ``pulses`` pulses; every
    feature of ALL_FEATURES is sample effect (SD 1) + pulse noise (SD 2), plus ``shift``
    ((species, feature) -> added mean) in every dataset. E_below's noise (both parts) is
    correlated ``rho`` with E's."""
    shift = shift or {}
    e, below = ALL_FEATURES.index("E"), ALL_FEATURES.index("E_below")
    rows = []
    for sp in SPECIES:
        for j in range(samples):
            u = rng.normal(0.0, 1.0, len(ALL_FEATURES))
            for ds in ("d1", "d2"):
                x = u + rng.normal(0.0, 2.0, (pulses, len(ALL_FEATURES)))
                x[:, below] = rho * x[:, e] + math.sqrt(1.0 - rho**2) * x[:, below]
                x += 10.0
                for k, f in enumerate(ALL_FEATURES):
                    x[:, k] += shift.get((sp, f), 0.0)
                t = pd.DataFrame(x, columns=list(ALL_FEATURES))
                t["dataset"], t["species"], t["sample_id"] = ds, sp, f"{sp}{j}"
                rows.append(t)
    return pd.concat(rows, ignore_index=True)


def _pair(seed: int, shift: dict | None = None, rho: float = 0.0):
    """(real, sim, universe, weights): real with ``shift``, sim without, 200 bootstrap replicates."""
    rng = np.random.default_rng(seed)
    real, sim = _table(rng, shift, rho=rho), _table(rng, rho=rho)
    universe = sample_universe(real, sim)
    return real, sim, universe, bootstrap_weights(universe, 200, seed)


SHIFT = {("birch", "E_below"): 1.3, ("birch", "D_mean"): 1.3}
"""An effect on two of 13 x 3 label x feature cells: 0.6 SDs of birch's energy below the first echo."""


def _signature(shift: dict) -> pd.Series:
    """The terms of the shift itself (noise-free: the expected d of each term)."""
    real, sim, universe, _ = _pair(0)
    point, _ = terms(real, sim, universe, **KW)
    sig = pd.Series(0.0, index=point.index)
    for (sp, f), v in shift.items():
        sig[(sp, f, "d")] = -v / 2.24  # d = (sim - real) / pooled SD, pooled SD ~ sqrt(1 + 4)
    return sig


def test_critical_value_is_the_two_sided_bonferroni_normal_quantile():
    assert critical_value(1, 0.05) == pytest.approx(1.959964, abs=1e-6)
    assert critical_value(10, 0.01) == pytest.approx(3.290527, abs=1e-6)
    assert critical_value(10) == critical_value(10, ALPHA)
    assert critical_value(1, 0.05, df=10) == pytest.approx(2.228139, abs=1e-6)  # Student t, 10 df


def test_terms_are_the_label_pooled_d_and_l_of_every_feature():
    real, sim, universe, w = _pair(1)
    point, boot = terms(real, sim, universe, w, **KW)
    assert len(point) == 2 * len(SPECIES) * len(ALL_FEATURES) and boot.shape == (200, len(point))
    assert set(point.index.get_level_values("moment")) == {"d", "log_sd_ratio"}
    # d of one label x feature is the mean over the datasets of (mean sim - mean real) / pooled SD
    sel = lambda t, ds: t[(t["species"] == "pine") & (t["dataset"] == ds)]["E"]  # noqa: E731
    d = [(sel(sim, ds).mean() - sel(real, ds).mean())
         / math.sqrt((sel(sim, ds).var() * (len(sel(sim, ds)) - 1) + sel(real, ds).var() * (len(sel(real, ds)) - 1))
                     / (len(sel(sim, ds)) + len(sel(real, ds)) - 2)) for ds in ("d1", "d2")]
    assert point[("pine", "E", "d")] == pytest.approx(np.mean(d), rel=1e-9)


def test_without_effect_z_has_unit_spread():
    """The bootstrap SD of the projection is the projection's SD: over 30 independent data sets
    without effect (20 field samples per species), the RMS of z lies near 1 (its sampling SD is
    about 0.13) and its mean near 0."""
    sig = _signature(SHIFT)
    off = [terms(*_pair(100 + i), **KW) for i in range(8)]
    test = replace(SignatureTest.calibrate({"e": sig}, off), scale={"e": 1.0})
    z = np.array([test.z(*terms(*_pair(200 + i), **KW))["e"] for i in range(30)])
    assert 0.7 < math.sqrt(np.mean(z**2)) < 1.3
    assert abs(np.mean(z)) < 0.5


def test_a_few_shifted_terms_fire_the_signature_test_and_not_the_gap():
    """A shift of two of 39 label x feature cells (E_below correlated 0.9 with E, as energy
    statistics are): the signature test (ten candidates, family rate 0.01) fires in at least
    80 % of 15 data sets, the omnibus gap over the same features in at most 40 %; without the
    shift the signature test never fires."""
    sig = _signature(SHIFT)
    rng = np.random.default_rng(5)
    decoys = {f"decoy{i}": pd.Series(rng.normal(0, 0.3, len(sig)), index=sig.index) for i in range(9)}
    off = [terms(*_pair(300 + i, rho=0.9), **KW) for i in range(10)]
    df = cluster_df(_pair(0)[2])
    test = SignatureTest.calibrate({"e": sig, **decoys}, off, df=df)
    assert all(c >= 1.0 for c in test.scale.values()) and test.crit == pytest.approx(critical_value(10, ALPHA, df))
    fired, gap_fired, null_fired = 0, 0, 0
    for i in range(15):
        real, sim, universe, w = _pair(400 + i, SHIFT, rho=0.9)
        margin, best = test.margin(*terms(real, sim, universe, w, **KW))
        fired += margin > 0 and best == "e"
        rep = gap_report(real, sim, features=ALL_FEATURES, universe=universe, weights=w, wasserstein=False, **KW)
        gap_fired += bool(rep.significant)
        null_fired += test.margin(*terms(*_pair(500 + i, rho=0.9), **KW))[0] > 0
    assert fired >= 12 and gap_fired <= 6 and null_fired == 0


def test_correlated_terms_are_read_against_their_difference():
    """E_below correlated 0.9 with E, an effect on E_below alone: the projection on V^-1 s sees it
    against the part of E_below that E does not predict, with SD sqrt(1 - 0.81) = 0.44 of its
    own, so its z is larger than with the variances alone (lambda = 1): by 1 / 0.44 = 2.3 at
    most (two terms, their correlation known), by about 1.5 here, where R* is estimated over
    78 terms from 10 data sets; without the effect both z keep unit spread."""
    shift = {("birch", "E_below"): 0.6}
    sig = _signature(shift)
    off = [terms(*_pair(700 + i, rho=0.9), **KW) for i in range(10)]
    corr = SignatureTest.calibrate({"e": sig}, off)
    r = corr.null_corr.loc[("birch", "E", "d"), ("birch", "E_below", "d")]
    assert r == pytest.approx(0.8 * 0.9, abs=0.1)  # (1 - lambda) x the terms' correlation
    variances = SignatureTest.calibrate({"e": sig}, off, shrinkage=1.0)
    assert (variances.null_corr.to_numpy() == np.eye(len(sig))).all()
    z = np.array([[t.z(*terms(*_pair(800 + i, shift, rho=0.9), **KW))["e"] for t in (corr, variances)]
                  for i in range(12)])
    assert 1.3 < np.mean(z[:, 0]) / np.mean(z[:, 1]) < 2.3
    z0 = np.array([[t.z(*terms(*_pair(900 + i, rho=0.9), **KW))["e"] for t in (corr, variances)]
                   for i in range(12)])
    assert (0.6 < np.sqrt(np.mean(z0**2, axis=0))).all() and (np.sqrt(np.mean(z0**2, axis=0)) < 1.4).all()


def test_calibration_corrects_a_bootstrap_that_understates_the_noise_and_never_shrinks_it():
    sig = _signature(SHIFT)
    off = [terms(*_pair(600 + i), **KW) for i in range(12)]
    honest = SignatureTest.calibrate({"e": sig}, off)
    # bootstrap replicates pulled halfway to their point estimates: z doubles
    narrow = [(p, p.to_numpy() + 0.5 * (b - p.to_numpy())) for p, b in off]
    tight = SignatureTest.calibrate({"e": sig}, narrow)
    assert honest.scale["e"] >= 1.0 and 1.5 < tight.scale["e"] / max(honest.scale["e"], 0.9) < 2.6
    rec = tight.read(*off[0])
    assert set(rec) == {"fires", "margin", "effect", "threshold", "z", "scale"} and rec["effect"] == "e"
    assert rec["fires"] == (abs(rec["z"]["e"]) / rec["scale"]["e"] > rec["threshold"])


def test_the_signature_test_only_adds_detections_to_the_limits():
    """Detection is the gap's test or the signature test: every candidate's power at every value
    tried is at least that of the gap's test alone, and its limit no larger."""
    study = SyntheticStudy(samples_per_species=12, pulses_per_sample=8, seed=1)
    settings = SearchSettings(n_boot=100, candidates=("hotspot", "understory"))
    power = PowerSettings(replicates=6, values=3, power=0.8)
    with_sig, curve = detection_limits(study.keys, study.simulate, settings, power, 3)
    alone, curve0 = detection_limits(study.keys, study.simulate, replace(settings, signature_alpha=None), power, 3)
    both = curve.merge(curve0, on=["effect", "value"], suffixes=("", "_gap"))
    assert len(both) >= 4 and (both["detected"] >= both["detected_gap"]).all()
    assert curve0["signature_margin"].isna().all() and curve["signature_margin"].notna().all()
    for name, a, b in zip(alone["effect"], with_sig["smallest_detectable"], alone["smallest_detectable"]):
        if np.isfinite(b):
            off = cat.effect(name).off
            assert np.isfinite(a) and abs(a - off) <= abs(b - off) + 1e-12
