"""End to end: `waveforest synthesize` writes a campaign folder that the pipeline reads.

A tiny campaign (two datasets, three species, few pulses and rays) keeps these tests fast;
the recovery of the true AGC law and S(t) at full density is in test_campaign_recovery.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from waveforest import config
from waveforest.effects import CATALOGUE

veg = pytest.importorskip("waveforest.vegetation")
if not hasattr(veg, "build_scene"):
    pytest.skip("waveforest.vegetation.build_scene is not available yet", allow_module_level=True)
pytest.importorskip("waveforest.mcrt")
las_write = pytest.importorskip("waveforest.io.las.write")

from waveforest.campaign import run  # noqa: E402
from waveforest.settings import campaign_settings  # noqa: E402

SMALL = {
    "seed": 11,
    "datasets": ["2010_12_1", "2012_10_1"],
    "campaign": {"samples_per_species": 1, "species": ["birch", "raspberry", "sand_road"],
                 "density_scale": 0.5, "n_rays": 300, "max_pulses_per_site": 14},
}
"""The tiny campaign of these tests (about 300 pulses, a few seconds)."""

XY_TEST = CATALOGUE["xy_error"].test_value
AR_TEST = CATALOGUE["noise_autocorr"].test_value


def small_cfg(**campaign) -> dict:
    raw = yaml.safe_load(yaml.safe_dump(SMALL))
    raw["campaign"].update(campaign)
    return config.validate(raw)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    out = tmp_path_factory.mktemp("base") / "campaign"
    summary = run(campaign_settings(small_cfg()), out, progress=False)
    return out, summary


@pytest.fixture(scope="module")
def truth(base):
    return json.loads((base[0] / "truth.json").read_text())


@pytest.fixture(scope="module")
def ingested(base, tmp_path_factory):
    from waveforest.io.las.pulses import las_to_pulses as ingest
    from waveforest.io.pulses import read_pulses

    out = tmp_path_factory.mktemp("pulses")
    tables = {}
    for ds in SMALL["datasets"]:
        path = out / f"{ds}.parquet"
        ingest(base[0] / f"{ds}.las", path, dataset=ds, trajectory=base[0] / f"{ds}_trajectory.csv")
        tables[ds] = read_pulses(path)
    return tables


def test_folder_has_every_file_with_its_schema(base):
    out, summary = base
    names = {p.name for p in out.iterdir()}
    expect = {"datasets.csv", "fields.csv", "targets.csv", "README.md", "truth.json", "truth_pulses.parquet",
              ".waveforest"}
    expect |= {f"{d}.las" for d in SMALL["datasets"]} | {f"{d}_trajectory.csv" for d in SMALL["datasets"]}
    assert names == expect
    assert not any(p.name.startswith(".") for p in out.parent.iterdir())  # no temporary folder left
    ds = pd.read_csv(out / "datasets.csv")
    assert list(ds.columns) == ["dataset", "year", "las_file", "trajectory_file", "mean_range_m",
                                "pulse_width_fwhm_ns", "footprint_diameter_m", "divergence_mrad", "sampling_ns",
                                "pulse_density_m2", "max_scan_zenith_deg"]
    assert list(ds["dataset"]) == SMALL["datasets"] and list(ds["year"]) == [2010, 2012]
    f = pd.read_csv(out / "fields.csv")
    assert list(f.columns) == ["sample_id", "year", "stand_id", "design", "species", "functional_group", "x", "y",
                               "ground_z", "height_m", "radius_m", "is_tree", "canopy_cover_pct"]
    assert sorted(f["species"].unique()) == ["birch", "raspberry", "sand_road"]
    t = pd.read_csv(out / "targets.csv")
    assert list(t.columns) == ["target_id", "year", "material", "hdrf", "calibration", "agc", "x", "y", "z",
                               "radius_m"]
    assert len(t) == 15  # 2010: 3 tarps, asphalt, sand + 4 AGC targets; 2012: asphalt, sand + 4
    assert summary.pulses and all(v > 0 for v in summary.pulses.values())
    tables = pytest.importorskip("waveforest.io.tables")
    tables.read_datasets(out / "datasets.csv")
    tables.read_fields(out / "fields.csv")
    tables.read_targets(out / "targets.csv")


def test_same_seed_gives_byte_identical_files(base, tmp_path):
    again = tmp_path / "again"
    run(campaign_settings(small_cfg()), again, progress=False)
    for name in [f"{d}.las" for d in SMALL["datasets"]] + ["fields.csv", "targets.csv", "2010_12_1_trajectory.csv"]:
        assert (base[0] / name).read_bytes() == (again / name).read_bytes(), name


def test_las_files_pass_laspy_and_ingest(base, truth, ingested):
    laspy = pytest.importorskip("laspy")
    for ds in SMALL["datasets"]:
        las = laspy.read(base[0] / f"{ds}.las")
        assert str(las.header.version) == "1.4" and las.header.point_format.id == 9
        assert len(las.points) == truth["datasets"][ds]["n_points"]
        assert np.all(np.asarray(las.intensity) <= 255)
        t = ingested[ds]
        assert t.num_rows == truth["datasets"][ds]["n_pulses"]
        agc = t.column("agc").to_numpy()
        assert np.mean(agc) == pytest.approx(truth["datasets"][ds]["a"])
        assert set(np.diff(t.column("samples").combine_chunks().offsets.to_numpy())) == {256}
        # ingested sensor positions (from the trajectory) = the true ones + the strip offsets
        tp = pd.read_parquet(base[0] / "truth_pulses.parquet")
        tp = tp[(tp["dataset"] == ds) & tp["recorded"]].set_index("gps_time")
        gps = t.column("gps_time").to_numpy()
        strips = truth["datasets"][ds]["strips"]
        off = np.array([strips[k]["offset_xyz_m"] for k in tp.loc[gps, "strip"]])
        sensor = np.column_stack([t.column(c).to_numpy() for c in ("sensor_x", "sensor_y", "sensor_z")])
        true = tp.loc[gps, ["sensor_x", "sensor_y", "sensor_z"]].to_numpy() + off
        assert np.abs(sensor - true).max() < 1e-3
        # range to the first echo = the sensor's DR range (true first-echo range, walk and jitter included)
        assert np.allclose(t.column("range_m").to_numpy(), tp.loc[gps, "first_echo_range_m"], atol=2e-3)


def test_truth_manifest(base, truth):
    assert truth["seed"] == SMALL["seed"]
    assert set(truth["effects"]) == set(CATALOGUE)
    assert all(truth["effects"][k] == e.off for k, e in CATALOGUE.items()) and truth["active_effects"] == {}
    for ds in SMALL["datasets"]:
        d = truth["datasets"][ds]
        agc = d["agc"]
        assert d["b"] == pytest.approx(agc["law_b"] / (1 + (d["a"] - agc["law_a"]) * agc["law_b"]))
        assert d["a"] == pytest.approx(agc["a_mean"])
        s = np.array(d["system_waveform"]["s"])
        t_ns = np.array(d["system_waveform"]["t_ns"])
        assert s.shape == t_ns.shape and np.allclose(np.diff(t_ns), 0.05)
        assert np.allclose(d["system_waveform"]["s_at_a_mean"], s * agc["gain_at_a_mean"])
        assert d["pulse_fwhm_ns"] == pytest.approx({"2010_12_1": 7.2, "2012_10_1": 10.1}[ds], rel=0.01)
        assert d["noise_sd_dn"] > 0 and d["sensor"]["range_walk"]["coef_m"] != 0
    assert "tarp_041_2010" in truth["targets"] and truth["targets"]["tarp_041_2010"]["true_rho"] == 0.41
    assert (base[0] / "README.md").read_text().count("| column |") == 3


def test_xy_error_moves_recorded_positions_only(base, ingested, tmp_path):
    from click.testing import CliRunner

    from waveforest.cli import cli
    from waveforest.io.las.pulses import las_to_pulses as ingest
    from waveforest.io.pulses import list_to_padded, read_pulses

    cfg_path = tmp_path / "config.yaml"
    cfg_path.write_text(yaml.safe_dump(SMALL))
    out = tmp_path / "xy"
    res = CliRunner().invoke(cli, ["synthesize", "--config", str(cfg_path), "--out", str(out), "--quiet",
                                   "--effect", f"xy_error={XY_TEST}"])
    assert res.exit_code == 0, res.output
    assert "hidden effects: xy_error=0.25" in res.output
    ds = "2012_10_1"
    ingest(out / f"{ds}.las", tmp_path / "xy.parquet", dataset=ds, trajectory=out / f"{ds}_trajectory.csv")
    moved, still = read_pulses(tmp_path / "xy.parquet"), ingested[ds]
    assert moved.num_rows == still.num_rows
    assert np.array_equal(list_to_padded(moved.column("samples"))[0], list_to_padded(still.column("samples"))[0])
    dx = np.column_stack([list_to_padded(moved.column(c), dtype=np.float64)[0][:, 0]
                          - list_to_padded(still.column(c), dtype=np.float64)[0][:, 0] for c in ("echo_x", "echo_y")])
    dz = (list_to_padded(moved.column("echo_z"), dtype=np.float64)[0][:, 0]
          - list_to_padded(still.column("echo_z"), dtype=np.float64)[0][:, 0])
    assert np.abs(dz).max() < 2e-3
    tp = pd.read_parquet(out / "truth_pulses.parquet")
    tp = tp[(tp["dataset"] == ds) & tp["recorded"]].set_index("gps_time").loc[moved.column("gps_time").to_numpy()]
    assert np.allclose(dx, tp[["xy_offset_x", "xy_offset_y"]].to_numpy(), atol=2e-3)
    # the written trajectory drifted with the points: the ingested sensors moved by the same offset
    ds_xy = np.column_stack([moved.column(c).to_numpy() - still.column(c).to_numpy() for c in ("sensor_x", "sensor_y")])
    assert np.allclose(ds_xy, dx, atol=2e-3)
    assert json.loads((out / "truth.json").read_text())["active_effects"] == {"xy_error": XY_TEST}


def test_noise_autocorr_shows_in_the_ingested_noise(base, ingested, tmp_path):
    from waveforest.io.las.pulses import las_to_pulses as ingest
    from waveforest.io.pulses import list_to_padded, read_pulses

    out = tmp_path / "ar"
    run(campaign_settings(small_cfg()), out, effects=[f"noise_autocorr={AR_TEST}"], progress=False)
    ds = "2010_12_1"
    ingest(out / f"{ds}.las", tmp_path / "ar.parquet", dataset=ds, trajectory=out / f"{ds}_trajectory.csv")
    truth = json.loads((out / "truth.json").read_text())["datasets"][ds]
    var = truth["noise_sd_dn"] ** 2
    for table, phi in ((ingested[ds], 0.0), (read_pulses(tmp_path / "ar.parquet"), AR_TEST)):
        s, _ = list_to_padded(table.column("samples"), dtype=np.float64)
        dev = s[:, -50:] - truth["noise_mean_dn"]
        lag1 = np.sum(dev[:, 1:] * dev[:, :-1]) / np.sum(dev**2)
        assert lag1 == pytest.approx(phi * var / (var + 1 / 12), abs=0.05)


def test_bad_input_is_one_clear_error_and_keeps_the_old_folder(tmp_path, capsys):
    from waveforest.cli import main

    out = tmp_path / "campaign"
    out.mkdir()
    (out / "keep.txt").write_text("old")
    cfg_path = tmp_path / "config.yaml"
    cfg_path.write_text(yaml.safe_dump(SMALL))
    for bad, message in ((["--effect", "fog=1"], "effect 'fog': unknown"),
                         (["--effect", "trigger_loss=1.5"], "trigger_loss = 1.5: expected a value in [0, 1)")):
        with pytest.raises(SystemExit) as exc:
            main(["synthesize", "--config", str(cfg_path), "--out", str(out), "--quiet", *bad])
        assert exc.value.code == 1
        assert message in capsys.readouterr().err
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
    raw = yaml.safe_load(yaml.safe_dump(SMALL))
    raw["datasets"] = ["2010_12_1", "2011_99_1"]
    cfg_path.write_text(yaml.safe_dump(raw))
    with pytest.raises(SystemExit):  # --force passes the folder check; the failing run still keeps the folder
        main(["synthesize", "--config", str(cfg_path), "--out", str(out), "--quiet", "--force"])
    assert "2011_99_1" in capsys.readouterr().err
    assert (out / "keep.txt").read_text() == "old"


def test_existing_folder_is_replaced_only_if_synthesize_wrote_it(base, tmp_path):
    from waveforest.atomic import FolderNotOursError

    out = tmp_path / "c"
    out.mkdir()
    (out / "stale.txt").write_text("x")
    settings = campaign_settings(small_cfg(species=["sand_road"], max_pulses_per_site=3))
    with pytest.raises(FolderNotOursError, match="holds stale.txt, which synthesize did not write"):
        run(settings, out, progress=False)
    assert (out / "stale.txt").exists()
    run(settings, out, progress=False, force=True)
    assert not (out / "stale.txt").exists() and (out / "truth.json").exists()
    assert Path(out / "2010_12_1.las").stat().st_size > 0
    first = (out / "2010_12_1.las").read_bytes()
    run(settings, out, progress=False)  # its own earlier campaign: replaced without --force
    assert (out / "2010_12_1.las").read_bytes() == first


def test_waveforest_info_summarises_the_las_files(base, truth):
    """``waveforest info`` (lasinfo-style): version, point format, the 8-bit descriptor, counts."""
    from click.testing import CliRunner

    from waveforest.cli import cli

    for ds in SMALL["datasets"]:
        d = truth["datasets"][ds]
        res = CliRunner().invoke(cli, ["info", str(base[0] / f"{ds}.las")])
        assert res.exit_code == 0, res.output
        text = res.output
        assert "LAS version:           1.4" in text
        assert "point format:          9 " in text
        assert f"points:                {d['n_points']:,} (header: {d['n_points']:,})" in text
        assert f"pulses (GPS times):    {d['n_pulses']:,}" in text
        assert f"packets:               {d['n_pulses']:,}" in text
        assert "1 defined, 1 in use" in text
        spacing_ps = int(round(1000 * {"2010_12_1": 1.0, "2012_10_1": 1.0}[ds]))
        assert any(line.split()[:5] == ["1", "8", "0", "256", str(spacing_ps)] for line in text.splitlines())
        assert "AGC attribute:         user_data" in text


def test_las_files_do_not_depend_on_the_thread_count(base, tmp_path):
    """Sites are traced ``--threads`` at a time; one at a time gives the same bytes."""
    import numba

    before = numba.get_num_threads()
    numba.set_num_threads(1)
    try:
        run(campaign_settings(small_cfg()), tmp_path / "serial", progress=False)
    finally:
        numba.set_num_threads(before)
    for name in [f"{d}.las" for d in SMALL["datasets"]] + ["truth_pulses.parquet"]:
        assert (base[0] / name).read_bytes() == (tmp_path / "serial" / name).read_bytes(), name


def test_out_that_is_not_a_folder_is_refused_at_once(tmp_path):
    """A FIFO (or device, or file) named as the campaign folder is refused before any work."""
    import os
    import stat

    from click.testing import CliRunner

    from waveforest.cli import cli

    fifo = tmp_path / "campaign"
    os.mkfifo(fifo)
    res = CliRunner().invoke(cli, ["synthesize", "--out", str(fifo), "--quiet"])
    assert res.exit_code != 0 and "not a folder" in str(res.exception or res.output)
    assert stat.S_ISFIFO(os.stat(fifo).st_mode) and sorted(p.name for p in tmp_path.iterdir()) == ["campaign"]


def test_design_campaign_records_samples_at_their_coverage_and_every_target():
    """Table 1's design counts: a species' (strip, sample) visits are kept at its coverage.csv rate;
    targets and a samples_per_species campaign are never thinned."""
    from waveforest.campaign.layout import build_layout
    from waveforest.campaign.params import coverage, load_datasets, load_layout
    from waveforest.campaign.synthesize import campaign_sites, plan_pulses

    ds = load_datasets(["2012_05_1"])
    lay = load_layout()
    layout = build_layout(veg.species_table(), None, 11)
    fields, targets = campaign_sites(layout, [2012], None)
    visits = {}
    for per_species in (None, 1000):  # design counts; a campaign with samples_per_species set
        cfg = small_cfg(samples_per_species=per_species, max_pulses_per_site=None, density_scale=1.0)
        _, pulses = plan_pulses(ds, fields, targets, layout, lay, campaign_settings(cfg))
        visits[per_species] = pulses["2012_05_1"].groupby(["site", "strip"]).size()
    full, thin = visits[1000], visits[None]
    species = full.index.get_level_values(0).map(fields.set_index("sample_id")["species"])
    kept = full.index.isin(thin.index)
    assert kept[species.isna()].all()  # targets
    for slug in ("raspberry", "fireweed", "birch", "scots_pine"):
        c = float(coverage("2012_05_1", [slug])[0])
        k = kept[species == slug]
        assert abs(k.mean() - c) <= 3 * np.sqrt(c * (1 - c) / k.size) + 1e-12, slug
    assert (thin.reindex(full.index[kept]) == full[kept]).all()  # a kept visit keeps all its pulses
