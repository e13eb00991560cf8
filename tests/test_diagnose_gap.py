"""The gap measure of waveforest.diagnose.gap: known answers, noise, interval coverage."""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from waveforest.diagnose import before_after as BA
from waveforest.diagnose import gap as G
from waveforest.errors import WaveforestError
from waveforest.stats import bootstrap as B

COVERAGE_TRIALS = 120
"""Null data sets drawn to check the coverage of the 95 % interval of d."""

COVERAGE_RANGE = (0.88, 0.995)
"""Acceptable coverage of a nominal 95 % interval in COVERAGE_TRIALS trials (binomial +-3 SE,
and a little room for the bootstrap's own bias)."""


def clustered(rng, *, datasets=("d1", "d2"), species=("a", "b"), samples=10, pulses=12, mean=0.0, sd=1.0,
              icc=0.3, shift=None, prefix="", feature="H"):
    """A feature table with between-sample correlation ``icc`` (total SD ``sd``).

    ``shift`` (dict feature -> value) is added to every pulse. Features: H (the values),
    Npeaks (constant 1), Apeak (independent normals, mean 80, SD 10).
    """
    rows = []
    for sp in species:
        for j in range(samples):
            sid = f"{prefix}{sp}{j:03d}"
            plant = rng.normal(0, sd * np.sqrt(icc))
            for ds in datasets:
                x = mean + plant + rng.normal(0, sd * np.sqrt(1 - icc), pulses)
                rows.append(pd.DataFrame({"dataset": ds, "species": sp, "sample_id": sid, "H": x,
                                          "Npeaks": 1.0, "Apeak": rng.normal(80, 10, pulses),
                                          "FWHM": rng.normal(6, 0.5, pulses), "E": rng.normal(500, 50, pulses)}))
    df = pd.concat(rows, ignore_index=True)
    for f, v in (shift or {}).items():
        df[f] = df[f] + v
    return df


def test_known_shift_gives_d_equal_to_shift_and_gap_k_squared():
    rng = np.random.default_rng(1)
    real = clustered(rng, samples=40, pulses=20, icc=0.0)
    sim = clustered(rng, samples=40, pulses=20, icc=0.0, shift={"H": 1.5})
    rep = G.gap_report(real, sim, n_boot=50, seed=2, features=("H",))
    d = rep.cells["d"].to_numpy()
    assert np.allclose(d, 1.5, atol=0.25)  # SE of d with 800 pulses per side ~ 0.057: 4 SE
    assert d.mean() == pytest.approx(1.5, abs=0.12)  # four cells: SE ~ 0.03
    assert rep.total == pytest.approx(1.5**2, rel=0.12)  # l ~ 0
    assert rep.significant



def test_datasets_are_pooled_before_squaring():
    """d and l are averaged over a species' datasets before squaring: a shift in every dataset
    counts k^2, the same shift in one of D datasets k^2 / D^2, opposite shifts cancel; the
    noise floor of D pooled datasets is about 1/D of one cell's."""
    rng = np.random.default_rng(13)
    ds = ("d1", "d2", "d3", "d4")
    real = clustered(rng, datasets=ds, species=("a",), samples=60, pulses=15, icc=0.0)
    base = clustered(rng, datasets=ds, species=("a",), samples=60, pulses=15, icc=0.0)
    k = 1.0

    def total(sim):
        return G.gap_report(real, sim, n_boot=100, seed=3, features=("H",), wasserstein=False)

    everywhere, one, opposite = base.copy(), base.copy(), base.copy()
    everywhere["H"] += k
    one.loc[one["dataset"] == "d1", "H"] += k
    opposite.loc[opposite["dataset"].isin(["d1", "d2"]), "H"] += k
    opposite.loc[opposite["dataset"].isin(["d3", "d4"]), "H"] -= k
    # per cell SE of d ~ sqrt(2 / 900) ~ 0.05, pooled ~ 0.024: allowances of ~3 SE
    assert total(everywhere).total == pytest.approx(k**2, abs=0.15)
    assert total(one).total == pytest.approx(k**2 / len(ds) ** 2, abs=0.05)
    rep = total(opposite)
    assert rep.cells["d"].abs().min() > 0.7  # every cell is far off ...
    assert rep.cells["log_sd_ratio"].abs().max() < 0.15
    assert rep.total < 0.03  # ... but not the same way in every dataset
    null = G.gap_report(real, base, n_boot=400, seed=3, features=("H",), wasserstein=False)
    cell_floor = null.cells["noise"].mean()
    assert null.noise_floor == pytest.approx(cell_floor / len(ds), rel=0.4)

def test_a_stratum_is_a_cell_of_its_own_and_keeps_its_samples():
    """Rows with a stratum form their own cells ("a below crown"); a shift there shows there
    only; the same samples hold pulses of both strata and are resampled as one cluster."""
    rng = np.random.default_rng(11)
    real = clustered(rng, species=("a",), samples=20, icc=0.0)
    sim = clustered(rng, species=("a",), samples=20, icc=0.0)
    for t in (real, sim):
        t["stratum"] = np.where(np.arange(len(t)) % 3 == 0, "below crown", "")
    sim.loc[sim["stratum"] != "", "H"] += 2.0
    rep = G.gap_report(real, sim, n_boot=50, seed=2, features=("H",))
    d = rep.cells.set_index(["dataset", "species"])["d"]
    assert sorted(rep.cells["species"].unique()) == ["a", "a below crown"]
    assert np.allclose(d.xs("a below crown", level="species"), 2.0, atol=0.5)
    assert np.allclose(d.xs("a", level="species"), 0.0, atol=0.3)
    assert len(G.sample_universe(real, sim)) == 20


def test_identical_distributions_gap_is_noise():
    rng = np.random.default_rng(3)
    real = clustered(rng, samples=12, icc=0.3)
    sim = clustered(rng, samples=12, icc=0.3)
    rep = G.gap_report(real, sim, n_boot=300, seed=4)
    tot = rep.summary.loc["total"]
    # the gap of two draws of one distribution is of the size of the noise floor ...
    assert 0.2 * tot["noise_floor"] < tot["gap"] < 4 * tot["noise_floor"]
    # ... and not significant
    assert not rep.significant
    assert tot["excess_ci_low"] < 0 < tot["excess_ci_high"]
    # every d interval of the H cells covers 0 or misses it rarely
    h = rep.cells[rep.cells["feature"] == "H"]
    assert ((h["d_ci_low"] < 0) & (h["d_ci_high"] > 0)).mean() >= 0.75


def test_constant_feature_uses_the_floor():
    rng = np.random.default_rng(5)
    real = clustered(rng, samples=6)
    sim = clustered(rng, samples=6, shift={"Npeaks": 0.1})
    rep = G.gap_report(real, sim, n_boot=30, seed=1, features=("Npeaks",))
    # both constant: pooled SD = floor 1/sqrt(12), d = 0.1 * sqrt(12), l = 0
    assert np.allclose(rep.cells["d"], 0.1 * np.sqrt(12.0))
    assert np.allclose(rep.cells["log_sd_ratio"], 0.0)
    assert np.isfinite(rep.total)


def test_sd_ratio_enters_the_gap():
    rng = np.random.default_rng(6)
    real = clustered(rng, samples=40, pulses=25, icc=0.0, species=("a",), datasets=("d",))
    sim = real.copy()
    sim["H"] = 2.0 * sim["H"]  # same mean 0, SD doubled
    rep = G.gap_report(real, sim, n_boot=30, seed=1, features=("H",))
    assert rep.cells["log_sd_ratio"].iloc[0] == pytest.approx(np.log(2.0), rel=1e-9)
    assert rep.total == pytest.approx(np.log(2.0) ** 2 + rep.cells["d"].iloc[0] ** 2)


def test_d_interval_has_nominal_coverage_under_the_null():
    """Clustered null data: the cluster bootstrap's 95 % interval of d covers 0 ~95 % of the time."""
    rng = np.random.default_rng(7)
    covered = 0
    for t in range(COVERAGE_TRIALS):
        real = clustered(rng, samples=8, pulses=10, icc=0.4, species=("a",), datasets=("d",))
        sim = clustered(rng, samples=8, pulses=10, icc=0.4, species=("a",), datasets=("d",), prefix="")
        rep = G.gap_report(real, sim, n_boot=150, seed=t, features=("H",), wasserstein=False)
        c = rep.cells.iloc[0]
        covered += bool(c["d_ci_low"] <= 0 <= c["d_ci_high"])
    cov = covered / COVERAGE_TRIALS
    assert COVERAGE_RANGE[0] <= cov <= COVERAGE_RANGE[1], cov


def test_cluster_bootstrap_is_wider_than_a_pulse_bootstrap_would_be():
    """Pulses of a sample are correlated: the interval must reflect samples, not pulses."""
    rng = np.random.default_rng(8)
    real = clustered(rng, samples=10, pulses=30, icc=0.6, species=("a",), datasets=("d",))
    sim = clustered(rng, samples=10, pulses=30, icc=0.6, species=("a",), datasets=("d",))
    rep = G.gap_report(real, sim, n_boot=300, seed=1, features=("H",), wasserstein=False)
    c = rep.cells.iloc[0]
    half_width = (c["d_ci_high"] - c["d_ci_low"]) / 2
    naive_se = np.sqrt(2.0 / 300)  # two independent means of 300 pulses, unit SD
    assert half_width > 3 * 1.96 * naive_se


def test_robust_sd_is_the_sd_of_normal_replicates_and_ignores_a_wild_one():
    """One replicate with a degenerate cell (a huge d^2) must not blow up an interval."""
    r = np.random.default_rng(3).normal(0.0, 2.0, (4000, 2))
    assert np.allclose(B.robust_sd(r), 2.0, rtol=0.05)
    r[0, 0] = 1e6
    assert B.robust_sd(r)[0] == pytest.approx(B.robust_sd(r[1:])[0], rel=0.01)
    lo, hi = B.wald_interval(np.zeros(2), r, df=30)
    assert hi[0] < 5.0 and lo[0] > -5.0
    lo, hi = B.recentred_interval(1.0, r[:, 0])
    assert lo < 1.0 < hi and hi - lo < 10.0
    assert np.isnan(B.robust_sd(np.array([[1.0], [np.nan]])))[0]


def test_gap_interval_is_the_recentred_one_clipped_at_zero():
    r = np.random.default_rng(4).normal(0.1, 1.0, 1000)
    raw = B.recentred_interval(0.05, r)
    assert raw[0] < 0 and G.gap_interval(0.05, r) == (0.0, raw[1])
    assert G.gap_interval(3.0, r) == B.recentred_interval(3.0, r)  # bounds above 0: untouched
    assert np.isnan(G.gap_interval(0.05, np.array([np.nan, 1.0]))).all()


def test_gap_intervals_stay_at_or_above_zero_and_the_excess_keeps_its_sign():
    """G >= 0: the intervals of the total, per-feature and per-cell gaps (before and after) never
    reach below 0; the excess G - F keeps negative bounds, and significance is the raw rule's."""
    rng = np.random.default_rng(3)
    real = clustered(rng, samples=6)
    sim = clustered(rng, samples=6)
    rep = G.gap_report(real, sim, n_boot=100, seed=4, wasserstein=False)
    s = rep.summary
    data = G.GapData.build(real, sim)
    w = B.bootstrap_weights(data.universe, 100, 4)
    raw_lows = []
    for f, row in s.iterrows():
        raw_lo, raw_hi = B.recentred_interval(row["gap"], G.total_gap(data, w, feature=None if f == "total" else f))
        raw_lows.append(raw_lo)
        assert row["ci_low"] == max(raw_lo, 0.0) and row["ci_high"] == raw_hi
        assert row["excess_ci_low"] == row["ci_low"] - row["noise_floor"]
        assert row["significant"] == bool(raw_lo - row["noise_floor"] > 0)  # clipping changes no verdict
    assert min(raw_lows) < 0  # the clipping was exercised
    assert (s["ci_low"] >= 0).all() and (s["excess_ci_low"] < 0).any()
    t = BA.before_after(real, sim, sim, n_boot=100, seed=4, wasserstein=False)
    lows = t[["before_ci_low", "after_ci_low"]].to_numpy()
    assert (lows >= 0).all() and (lows == 0).any() and (lows < t[["gap_before", "gap_after"]].to_numpy()).any()
    assert (t["before_ci_high"] >= t["gap_before"]).all()


def test_nanquantile0_is_numpys_nanquantile_bit_for_bit():
    """The one-sort quantile behind every bootstrap SE: NaN, +-inf, ties, all-NaN columns and
    single values, every quantile from 0 to 1."""
    rng = np.random.default_rng(5)
    q = [0.0, 0.025, 0.25, 0.5, 0.75, 0.975, 1.0, 0.3141]
    for _ in range(500):
        shape = (int(rng.integers(1, 60)),) + tuple(rng.integers(1, 5, size=rng.integers(0, 3)))
        x = rng.normal(size=shape) * 10 ** rng.uniform(-5, 5)
        x[rng.random(shape) < rng.uniform(0.0, 1.0)] = np.nan
        x[rng.random(shape) < 0.05] = np.inf
        x[rng.random(shape) < 0.05] = -np.inf
        if rng.random() < 0.3:
            x = np.round(x)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns, inf - inf
            ref = np.nanquantile(x, q, axis=0)
        assert np.array_equal(B.nanquantile0(x, q), ref, equal_nan=True)
    assert np.isnan(B.nanquantile0(np.empty((0, 3)), q)).all() and B.nanquantile0(np.empty((0, 3)), q).shape == (8, 3)


def test_bootstrap_weights_are_stratified_rescaled_and_seeded():
    uni = pd.Series(["a"] * 5 + ["b"] * 3, index=[f"s{i}" for i in range(8)])
    w = B.bootstrap_weights(uni, 40, seed=3)
    assert w.shape == (40, 8)
    assert np.all(w[:, :5].sum(axis=1) == 4) and np.all(w[:, 5:].sum(axis=1) == 2)
    assert np.array_equal(w, B.bootstrap_weights(uni, 40, seed=3))


def test_wasserstein_in_pooled_sds():
    rng = np.random.default_rng(9)
    real = clustered(rng, samples=30, pulses=30, icc=0.0, species=("a",), datasets=("d",))
    sim = real.copy()
    sim["H"] = sim["H"] + 0.8
    rep = G.gap_report(real, sim, n_boot=20, seed=1, features=("H",))
    c = rep.cells.iloc[0]
    assert c["w1"] == pytest.approx(0.8 / c["pooled_sd"], rel=1e-9)  # a pure shift moves W1 by the shift


def test_paired_reduction_detects_a_better_model():
    rng = np.random.default_rng(10)
    real = clustered(rng, samples=20)
    good = clustered(rng, samples=20)
    bad = good.copy()
    bad["H"] = bad["H"] + 1.5
    r = BA.paired_reduction(real, bad, good, n_boot=200, seed=1)
    assert r.reduction > 0 and r.ci_low > 0
    assert r.relative == pytest.approx(r.reduction / (r.gap_base - r.noise_base))
    same = BA.paired_reduction(real, good, good, n_boot=50, seed=1)
    assert same.reduction == 0 and same.ci_low == 0 == same.ci_high


def test_before_after_table():
    rng = np.random.default_rng(11)
    real = clustered(rng, samples=8)
    after = clustered(rng, samples=8)
    before = after.copy()
    before["Apeak"] = before["Apeak"] + 10.0  # one SD
    t = BA.before_after(real, before, after, n_boot=100, seed=2)
    assert set(t["level"]) == {"cell", "feature", "total"}
    cells = t[t["level"] == "cell"]
    assert len(cells) == 2 * 2 * 5  # datasets x species x features
    ap = t[(t["level"] == "feature") & (t["feature"] == "Apeak")].iloc[0]
    assert ap["gap_before"] > 0.4 and ap["reduction_ci_low"] > 0  # d ~ 1 per cell, SE ~ 0.2
    tot = t[t["level"] == "total"].iloc[0]
    assert tot["reduction"] == pytest.approx(tot["gap_before"] - tot["gap_after"])
    assert tot["before_ci_low"] <= tot["gap_before"] <= tot["before_ci_high"]
    h = t[(t["level"] == "feature") & (t["feature"] == "H")].iloc[0]
    assert h["reduction"] == pytest.approx(0.0, abs=1e-12)  # H untouched


def test_bad_input_is_one_clear_error():
    rng = np.random.default_rng(12)
    real = clustered(rng, samples=3)
    with pytest.raises(WaveforestError, match="missing column"):
        G.gap_report(real.drop(columns="E"), real)
    other = clustered(rng, samples=3, prefix="x")
    with pytest.raises(WaveforestError, match="not in the real table"):
        G.GapData.build(real, other, G.sample_universe(real))
    with pytest.raises(WaveforestError, match="no cell"):
        G.gap_report(real.head(5), real.head(5))
