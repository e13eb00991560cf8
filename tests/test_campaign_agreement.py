"""The campaign against the analysis model: agreement without effects, detection with each.

Issue 6, "Checked by": with no effect switched on, the MCRT + sensor simulation of the
selected pulses (``simulate``) and the campaign agree -- every Table 3 feature mean within
2 standard errors; each hidden effect, switched on at its catalogue test value, moves at least
one feature mean by more than 3 standard errors.

Both go through the real stages (synthesize -> ingest -> agc -> calibrate -> select ->
features; simulate -> features; compare.table3) on one 2012 dataset (sample radius 1 m) with
the three modelled species. The standard error of a difference of two means is
sqrt(se_1^2 + se_2^2), se = sd / sqrt(n), except that a campaign mean compared with a
simulation has a cluster-robust se over its field samples (:func:`_cluster_se`). An effect campaign uses the same seed as the baseline (the
same plants and pulses; only the effect differs) and is compared with the baseline campaign.
Slow: about 11 minutes in all (twelve campaigns, one simulation).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml

from waveforest import config
from waveforest.effects import CATALOGUE

pytestmark = pytest.mark.slow

AGREE_SE = 2.0
"""The issue's criterion: campaign and simulation feature means within this many SE."""

MOVE_SE = 3.0
"""The issue's criterion: an effect moves at least one feature mean by more than this many SE."""

DATASET = "2012_10_1"
SPECIES = ["birch", "raspberry", "fireweed"]
FEATURES = ("H", "Npeaks", "Apeak", "FWHM", "E")

RAW = {
    "seed": 21,
    "datasets": [DATASET],
    "campaign": {"samples_per_species": 12, "species": SPECIES, "n_rays": 1000},
    "mcrt": {"n_rays": 1000},
    "calibrate": {"cos_incidence": True},
    "select": {"min_pulses": 5},
    "simulate": {"species": SPECIES, "datasets": [DATASET], "chunks": 1},
}
"""One 2012 dataset, twelve samples of each modelled species, 1000 rays per pulse on both sides.
Each campaign sample is one plant, while ``simulate`` gives every pulse a new one: the campaign
mean carries the spread between plants. With six birches the simulated birch FWHM was 3.0 SE
above the campaign's (15.1 vs 12.2 ns); simulating the campaign's own six plants instead gave
12.8 vs 12.3 ns, so the sensor and MCRT chains agree and six trees were too few. With twelve
and the naive SE, fireweed H is 2.07 SE apart (1.008 vs 1.081 m, twelve plots); with the
cluster-robust SE of the campaign mean (:func:`_table`) every feature is within 2 SE.
The campaign's reference targets are Lambertian (sigma = rho cos(incidence) / pi), so the
calibration takes the incidence into account (``calibrate.cos_incidence``); without it S(t) is
about 1.5 % low at the 0-15 degree scan zeniths and so is every simulated amplitude."""


EFFECT_CAMPAIGN = {"samples_per_species": 28, "density_scale": 4.5}
"""The effect tests' campaigns: twice the pulse density of :data:`RAW`, no simulation."""


def _cfg(**campaign) -> dict:
    raw = yaml.safe_load(yaml.safe_dump(RAW))
    raw["campaign"].update(campaign)
    return config.validate(raw)


def _real_features(tmp, cfg, effects=None, simulate=False):
    """Synthesize a campaign and run the real-data stages; optionally simulate its selection."""
    from waveforest.campaign import run as synthesize
    from waveforest.io.las.pulses import las_to_pulses as ingest
    from waveforest.io.results import attach_selection
    from waveforest.io.tables import read_datasets, read_targets
    from waveforest.settings import campaign_settings
    from waveforest.stages import agc as agc_stage
    from waveforest.stages import calibrate as calibration
    from waveforest.stages import features, select
    from waveforest.stages import simulate as sim_stage

    camp = tmp / "campaign"
    synthesize(campaign_settings(cfg), camp, effects=effects, progress=False)
    targets, datasets = read_targets(camp / "targets.csv"), read_datasets(camp / "datasets.csv")
    ingest(camp / f"{DATASET}.las", tmp / "pulses.parquet", dataset=DATASET,
           trajectory=camp / f"{DATASET}_trajectory.csv")
    agc_stage.run(tmp / "pulses.parquet", targets, datasets, tmp / "agc.parquet", tmp / "agc.json", cfg,
                  progress=False)
    calibration.run(tmp / "agc.parquet", targets, datasets, tmp / "S.parquet", tmp / "S.json", cfg, progress=False)
    select.run(tmp / "agc.parquet", camp / "fields.csv", camp / "datasets.csv", tmp / "select.parquet", cfg)
    sel = pd.read_parquet(tmp / "select.parquet", columns=["dataset", "pulse_id", "species", "comparison_set"])
    real = features.run([tmp / "select.parquet"], [tmp / "S.json"], tmp / "real.parquet", cfg, progress=False)
    real = attach_selection(real, sel)
    real = real[real["species"].isin(SPECIES) & real["comparison_set"].fillna(False).astype(bool)]
    if not simulate:
        return real, None
    sim_stage.run(tmp / "select.parquet", camp / "datasets.csv", tmp / "S.parquet", tmp / "S.json",
                  tmp / "sim.parquet", cfg, fields_path=camp / "fields.csv")
    sim = features.run([tmp / "sim.parquet"], [tmp / "S.json"], tmp / "sim_features.parquet", cfg, progress=False)
    return real, sim[sim["species"].isin(SPECIES)]


def _cluster_se(values: np.ndarray, clusters: np.ndarray) -> float:
    """Standard error of the mean of clustered values (cluster-robust, CR1):
    sqrt(G / (G - 1) * sum_g (sum_{i in g} (x_i - mean))^2) / n, G clusters, n values."""
    ok = np.isfinite(values)
    x, g = values[ok], clusters[ok]
    _, inv = np.unique(g, return_inverse=True)
    n_g = int(inv.max()) + 1 if inv.size else 0
    if n_g < 2:
        return float("nan")
    s = np.bincount(inv, weights=x - x.mean())
    return float(np.sqrt(n_g / (n_g - 1) * np.sum(s**2)) / x.size)


def _table(a: pd.DataFrame, b: pd.DataFrame, cfg, cluster_a: bool = False) -> pd.DataFrame:
    """Table 3 of ``b`` (as 'sim') against ``a`` (as 'real') with the SE of each difference.

    ``cluster_a``: the SE of ``a``'s mean is cluster-robust over field samples. A campaign's
    pulses on one sample all see the same plant, while ``simulate`` gives every pulse a plant
    of its own, so the campaign mean also carries the spread between plants."""
    from waveforest.analysis.compare import h_filter, table3

    min_h = {k: float(v) for k, v in cfg["simulate"]["compare_min_h_m"].items()}
    t = table3(a, b, min_h, FEATURES)
    se_a = t["real_sd"] / np.sqrt(t["n_real"])
    if cluster_a:
        wf = h_filter(a, min_h)
        for i, row in t.iterrows():
            rows = (a["dataset"] == row["dataset"]) & (a["species"] == row["species"])
            if row["feature"] != "H":
                rows &= wf
            se_a[i] = _cluster_se(a.loc[rows, row["feature"]].to_numpy(float), a.loc[rows, "sample_id"].to_numpy())
    t["se"] = np.sqrt(t["sim_sd"] ** 2 / t["n_sim"] + se_a**2)
    t["z"] = t["delta"] / t["se"]
    return t


@pytest.fixture(scope="module")
def baseline(tmp_path_factory):
    pytest.importorskip("waveforest.vegetation")
    pytest.importorskip("waveforest.stages.simulate")
    cfg = _cfg()
    real, sim = _real_features(tmp_path_factory.mktemp("baseline"), cfg, simulate=True)
    return cfg, real, sim


def test_simulation_and_campaign_agree_without_effects(baseline):
    cfg, real, sim = baseline
    t = _table(real, sim, cfg, cluster_a=True)
    assert set(t["species"]) == set(SPECIES)
    assert (t["n_real"] >= 20).all() and (t["n_sim"] >= 20).all(), t[["species", "feature", "n_real", "n_sim"]]
    bad = t[~(t["z"].abs() <= AGREE_SE)]
    assert bad.empty, "feature means more than 2 SE apart:\n" + bad.to_string()


@pytest.fixture(scope="module")
def effect_baseline(tmp_path_factory):
    pytest.importorskip("waveforest.vegetation")
    cfg = _cfg(**EFFECT_CAMPAIGN)
    real, _ = _real_features(tmp_path_factory.mktemp("effect_baseline"), cfg)
    return cfg, real


@pytest.mark.parametrize("name", list(CATALOGUE))
def test_each_effect_moves_a_feature(effect_baseline, name, tmp_path):
    cfg, real = effect_baseline
    value = CATALOGUE[name].test_value
    moved, _ = _real_features(tmp_path, cfg, effects={name: value})
    t = _table(real, moved, cfg)
    top = t.loc[t["z"].abs().idxmax()]
    print(f"\n{name}={value}: largest shift {top['species']} {top['feature']} {top['z']:+.1f} SE")
    assert abs(top["z"]) > MOVE_SE, (f"{name}={value}: largest shift {top['species']} {top['feature']} "
                                     f"{top['z']:+.1f} SE\n" + t.to_string())
