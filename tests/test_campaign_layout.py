"""Layout of the virtual campaign: stands, field samples, targets; flights and pulse placement."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import quad
from scipy.spatial.distance import pdist

from waveforest.campaign.flight import mean_secant, plan_flight, site_pulses
from waveforest.campaign.layout import FIELD_COLUMNS, Frame, build_layout, species_for_year
from waveforest.campaign.params import CampaignParamsError, load_datasets, load_design_counts, load_layout, load_targets
from waveforest.io.trajectory import Trajectory

SEED = 2014
MIN_SAMPLE_DISTANCE_M = 10.0
"""Samples 12 m apart on a grid, jittered by at most 1 m (layout.yaml)."""


@pytest.fixture(scope="module")
def species():
    veg = pytest.importorskip("waveforest.vegetation")
    if not hasattr(veg, "species_table"):
        pytest.skip("waveforest.vegetation.species_table is not available yet")
    return veg.species_table()


@pytest.fixture(scope="module")
def layout(species):
    return build_layout(species, 3, SEED)


def test_parameter_files_hold_table2_and_the_paper_targets():
    table2 = pd.DataFrame({
        "dataset": ["2010_12_1", "2010_19_1", "2010_19_2", "2010_30_1", "2010_30_2", "2012_05_1", "2012_10_1",
                    "2012_20_1", "2012_27_1"],
        "mean_range_m": [1200, 1957, 1957, 3022, 3021, 522, 1029, 2030, 2787],
        "pulse_width_fwhm_ns": [7.2, 7.2, 7.2, 10.1, 10.1, 7.7, 10.1, 10.3, 10.5],
        "footprint_diameter_m": [0.18, 0.29, 0.29, 0.45, 0.45, 0.08, 0.15, 0.30, 0.42],
        "sampling_ns": [1, 1, 2, 1, 2, 1, 1, 1, 1],
        "pulse_density_m2": [4.7, 2.7, 2.8, 0.9, 0.9, 5.2, 5.2, 3.1, 2.1]})
    ds = load_datasets()
    for col in table2.columns[1:]:
        assert np.allclose(ds[col], table2[col]), col
    assert list(ds["dataset"]) == list(table2["dataset"])
    assert np.all(ds["max_scan_zenith_deg"] == 15)
    # footprint (1/e) = range x divergence (docs/method.md §(a)), to Table 2's two decimals
    assert np.allclose(ds["mean_range_m"] * ds["divergence_mrad"] * 1e-3, ds["footprint_diameter_m"], atol=0.006)
    t = load_targets()
    tarps = t[t["material"] == "tarp"]
    assert sorted(tarps["hdrf"]) == [0.14, 0.21, 0.41]
    cal = t[t["calibration"] == 1].set_index("site")
    assert cal.loc["asphalt", "hdrf"] == 0.21 and cal.loc["sand", "hdrf"] == 0.34
    assert set(t.loc[t["agc"] == 1, "material"]) >= {"bitumen_roof", "old_asphalt", "fine_sand", "grass"}
    assert t.loc[t["calibration"] == 0, "hdrf"].isna().all()


def test_unknown_dataset_is_a_clear_error():
    with pytest.raises(CampaignParamsError, match="2011_10_1.*known: 2010_12_1"):
        load_datasets(["2011_10_1"])


def test_frame_round_trip():
    f = Frame(357500.0, 6861500.0, 160.0)
    s, w = np.array([0.0, 100.0, -20.0]), np.array([0.0, 5.0, 300.0])
    x, y = f.to_world(s, w)
    s2, w2 = f.to_frame(x, y)
    assert np.allclose(s, s2) and np.allclose(w, w2)
    # 100 m along track is 100 m towards azimuth 160 deg
    assert np.degrees(np.arctan2(x[1] - x[0] - 5 * f.v[0], y[1] - y[0] - 5 * f.v[1])) % 360 == pytest.approx(160.0)


def test_layout_follows_table1_and_method(layout, species):
    f = layout.fields
    assert list(f.columns[:len(FIELD_COLUMNS)]) == FIELD_COLUMNS
    assert f["sample_id"].is_unique
    merged = load_design_counts().merge(species, on="slug")
    for year in (2010, 2012):
        expect = set(species_for_year(merged, year)["slug"])
        got = f[f["year"] == year]
        assert set(got["species"]) == expect
        assert (got.groupby("species").size() == 3).all()
    assert {"sand_road", "birch", "raspberry", "fireweed"} <= set(f.loc[f["year"] == 2012, "species"])
    assert set(f.loc[f["year"] == 2010, "radius_m"]) == {0.5} and set(f.loc[f["year"] == 2012, "radius_m"]) == {1.0}
    info = species.set_index("slug")
    lo, hi = info.loc[f["species"], "min_h"].to_numpy(), info.loc[f["species"], "max_h"].to_numpy()
    assert np.all(f["height_m"].between(lo - 0.005, hi + 0.005))
    assert np.array_equal(f["is_tree"].to_numpy(), info.loc[f["species"], "is_tree"].to_numpy().astype(int))
    assert set(f.loc[f["year"] == 2012, "design"]) == {"S12"}
    assert set(f.loc[f["year"] == 2010, "design"]) <= {"P10", "S10"}
    assert set(f.loc[f["design"] == "P10", "is_tree"]) == {1}
    assert f.groupby("year")["stand_id"].nunique().to_dict() == {2010: 14, 2012: 13}
    # isolation: no two samples closer than 10 m (one 6 x 6 m scene per sample)
    assert pdist(f[["x", "y"]].to_numpy()).min() >= MIN_SAMPLE_DISTANCE_M
    t = layout.targets
    assert sorted(t.loc[t["year"] == 2010, "material"].unique()) == sorted(
        ["tarp", "asphalt", "sand", "bitumen_roof", "old_asphalt", "fine_sand", "grass"])
    assert sorted(t.loc[(t["year"] == 2012) & (t["calibration"] == 1), "material"]) == ["asphalt", "sand"]
    allxy = np.vstack([f[["x", "y"]].to_numpy(), t.drop_duplicates("site")[["x", "y"]].to_numpy()])
    assert pdist(allxy).min() >= MIN_SAMPLE_DISTANCE_M


@pytest.mark.parametrize("samples, seed", [(40, 1), (80, SEED)])
def test_large_campaigns_keep_samples_and_targets_isolated(species, samples, seed):
    """Stands of many samples are placed by their footprints: at 40 per species and year seed 1
    once put two stands' samples 2.4 m apart; 80 did not fit at all."""
    lay = build_layout(species, samples, seed)
    f, t = lay.fields, lay.targets.drop_duplicates("site")
    assert (f.groupby(["year", "species"]).size() == samples).all()
    assert pdist(f[["x", "y"]].to_numpy()).min() >= MIN_SAMPLE_DISTANCE_M
    # no sample pulse sees a target square, no target pulse sees a plant (layout.py isolation)
    d = np.hypot(*(t[["x", "y"]].to_numpy()[:, None, :] - f[["x", "y"]].to_numpy()[None, :, :]).transpose(2, 0, 1))
    need = np.maximum(t["side_m"] / np.sqrt(2) + 5.5, t["radius_m"] + 4.5 + 3 * np.sqrt(2)).to_numpy()
    assert (d.min(axis=1) >= need).all()


def test_too_many_samples_for_the_area_is_a_clear_error(species):
    with pytest.raises(CampaignParamsError, match="cannot place 27 stands of 300 samples.*samples_per_species"):
        build_layout(species, 300, SEED)


def test_layout_is_deterministic(layout, species):
    again = build_layout(species, 3, SEED)
    pd.testing.assert_frame_equal(layout.fields, again.fields)
    pd.testing.assert_frame_equal(layout.targets, again.targets)
    other = build_layout(species, 3, SEED + 1)
    assert not np.allclose(other.fields["x"].to_numpy()[:10], layout.fields["x"].to_numpy()[:10])


def test_mean_secant_is_the_swath_average():
    for deg in (5.0, 15.0, 30.0):
        t = np.tan(np.radians(deg))
        ref = quad(lambda x: np.sqrt(1 + x * x), -t, t)[0] / (2 * t)
        assert mean_secant(deg) == pytest.approx(ref, rel=1e-12)


@pytest.mark.parametrize("name", ["2010_12_1", "2012_05_1", "2010_30_2"])
def test_pulses_cover_every_site_at_the_dataset_density(layout, name):
    row = load_datasets([name]).iloc[0]
    lay = load_layout()
    f = layout.fields[layout.fields["year"] == row["year"]]
    sites = pd.DataFrame({"site": f["sample_id"], "s": f["s"], "w": f["w"], "ground_z": f["ground_z"],
                          "disc_m": f["radius_m"] + 0.7})
    plan = plan_flight(row, layout.frame, lay, 1.0, SEED, float(sites["ground_z"].mean()))
    p = site_pulses(plan, sites, lay, SEED)
    # every site is flown; scan zenith within 15 deg; unit directions towards the ground point
    assert set(p["site"]) == set(sites["site"])
    zen = np.degrees(np.arccos(-p["dir_z"]))
    assert zen.max() <= 15.0
    d = p[["ground_x", "ground_y", "ground_z"]].to_numpy() - p[["sensor_x", "sensor_y", "sensor_z"]].to_numpy()
    assert np.allclose(d / np.linalg.norm(d, axis=1)[:, None], p[["dir_x", "dir_y", "dir_z"]].to_numpy())
    assert np.allclose(np.linalg.norm(d, axis=1), p["range_ground_m"])
    # the mean range is Table 2's within the terrain's relief
    assert p["range_ground_m"].mean() == pytest.approx(row["mean_range_m"], rel=0.02)
    # ground points inside the discs; density = Table 2's, per strip that flies a site
    g = sites.set_index("site").loc[p["site"]]
    gx, gy = layout.frame.to_world(g["s"], g["w"])
    assert np.all(np.hypot(p["ground_x"] - gx, p["ground_y"] - gy) <= g["disc_m"].to_numpy() + 1e-9)
    visits = p.groupby(["site", "strip"]).size()
    area = np.pi * sites.set_index("site").loc[visits.index.get_level_values(0), "disc_m"].to_numpy() ** 2
    assert visits.sum() / area.sum() == pytest.approx(row["pulse_density_m2"], rel=0.1)
    # GPS times unique and increasing along each strip; strips in flight order
    assert p["gps_time"].is_unique and p["gps_time"].is_monotonic_increasing
    # the written trajectory reproduces every pulse's sensor position by linear interpolation
    traj = plan.trajectory(float(lay["flight"]["trajectory_hz"]))
    tr = Trajectory(traj["gps_time"].to_numpy(), traj[["x", "y", "z"]].to_numpy())
    pos = tr.position(p["gps_time"].to_numpy())
    assert np.abs(pos - p[["sensor_x", "sensor_y", "sensor_z"]].to_numpy()).max() < 1e-4
    # azimuths alternate 160 / 340
    assert [s.azimuth_deg for s in plan.strips][:2] == [160.0, 340.0]


def test_the_default_layout_has_table1_design_counts_and_keeps_samples_apart(species):
    """samples_per_species None: P10 + S10 samples per species in 2010, S12 in 2012 (Table 1)."""
    lay = build_layout(species, None, SEED)
    counts = load_design_counts().set_index("slug").fillna(0)
    got = lay.fields.groupby(["year", "species"]).size()
    for slug, row in counts.iterrows():
        assert got.get((2010, slug), 0) == int(row["P10"] + row["S10"]), slug
        assert got.get((2012, slug), 0) == int(row["S12"]), slug
    assert len(lay.fields) > 7000
    for _, f in lay.fields.groupby("stand_id"):
        assert pdist(f[["s", "w"]].to_numpy()).min() >= MIN_SAMPLE_DISTANCE_M
    heights = lay.fields.loc[lay.fields["species"] == "birch", "height_m"]
    assert heights.min() >= 1.5 and heights.max() <= 7.5 and heights.between(2.5, 5.0).mean() < 0.6


def _sites(fields: pd.DataFrame) -> pd.DataFrame:
    return pd.DataFrame({"site": fields["sample_id"].to_numpy(), "s": fields["s"].to_numpy(),
                         "w": fields["w"].to_numpy(), "ground_z": fields["ground_z"].to_numpy(),
                         "disc_m": fields["radius_m"].to_numpy() + 0.3})


def test_coverage_drops_whole_strip_visits_at_its_rate_and_keeps_the_rest_identical(species):
    """A site of coverage c keeps each (strip, site) visit with probability c; the visits kept,
    and every site of coverage 1, have exactly the pulses of the flight without coverage."""
    lay_ = build_layout(species, None, SEED)
    row = load_datasets(["2012_27_1"]).iloc[0]  # two strips over many sites: visits of both kinds
    lay = load_layout()
    sites = _sites(lay_.fields[lay_.fields["year"] == 2012])
    plan = plan_flight(row, lay_.frame, lay, 1.0, SEED, float(sites["ground_z"].mean()))
    full = site_pulses(plan, sites, lay, SEED)
    c = np.where(np.arange(len(sites)) % 3 == 0, 1.0, np.where(np.arange(len(sites)) % 3 == 1, 0.6, 0.0))
    thin = site_pulses(plan, sites.assign(coverage=c), lay, SEED)
    cov = dict(zip(sites["site"], c))
    visits_full = full.groupby(["site", "strip"]).size()
    visits_thin = thin.groupby(["site", "strip"]).size()
    c_visit = visits_full.index.get_level_values(0).map(cov).to_numpy(float)
    kept = visits_full.index.isin(visits_thin.index)
    assert kept[c_visit == 1].all() and not kept[c_visit == 0].any()
    k = kept[c_visit == 0.6]
    assert abs(k.mean() - 0.6) < 3 * np.sqrt(0.6 * 0.4 / k.size) and k.size > 500
    key = ["site", "strip", "gps_time"]
    same = full[full.set_index(["site", "strip"]).index.isin(visits_thin.index)]
    pd.testing.assert_frame_equal(same.sort_values(key).reset_index(drop=True),
                                  thin.sort_values(key).reset_index(drop=True))


def test_coverage_file_lookup_and_bad_values(tmp_path, monkeypatch):
    from waveforest.campaign import params
    assert params.coverage("2012_05_1", ["raspberry", "birch"]).tolist() == [0.57, 1.0]
    assert params.coverage("2012_10_1", np.array(["birch", "scots_pine"], object)).tolist() == [0.98, 0.70]
    assert np.all(params.coverage("2010_19_1", ["birch"]) == 1.0)
    for name in ("datasets.csv", "sensor_truth.csv", "design_counts.csv"):
        (tmp_path / name).write_text((params.CAMPAIGN_RESOURCES / name).read_text())
    monkeypatch.setattr(params, "CAMPAIGN_RESOURCES", tmp_path)
    cases = {"2012_05_1,birch,1.2\n": "coverage: expected numbers in \\[0, 1\\]",
             "2012_05_1,birch,\n": "coverage: expected numbers",
             "2013_05_1,birch,0.5\n": "dataset: unknown dataset\\(s\\) 2013_05_1",
             "2012_05_1,oak,0.5\n": "species: unknown slug\\(s\\) oak",
             "2012_05_1,birch,0.5\n2012_05_1,birch,0.6\n": "listed twice"}
    try:
        for body, msg in cases.items():
            (tmp_path / "coverage.csv").write_text("dataset,species,coverage\n" + body)
            params._coverage.cache_clear()
            with pytest.raises(CampaignParamsError, match=msg):
                params.coverage("2012_05_1", ["birch"])
    finally:
        params._coverage.cache_clear()
