"""The sensor stages as commands: waveforest agc | calibrate | features (CliRunner and main())."""

import json

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from reference_sensor import target_pulses, write_campaign_tables

from waveforest.cli import cli, main
from waveforest.io.pulses import write_pulses
from waveforest.sensor import gaussian_system_waveform

SYSTEM = gaussian_system_waveform(7.2, 2.0e9)


@pytest.fixture
def campaign(tmp_path):
    table, truth = target_pulses(np.random.default_rng(21), SYSTEM, per_target=40, b_true=0.01, n_other=30)
    n = table.num_rows
    src = write_pulses(table, tmp_path / "pulses.parquet")
    dpath, tpath = write_campaign_tables(tmp_path / "campaign")
    return tmp_path, src, dpath, tpath, truth, n


def test_help_lists_the_sensor_commands():
    res = CliRunner().invoke(cli, ["--help"])
    assert res.exit_code == 0
    for name in ("agc", "calibrate", "features"):
        assert name in res.output


def test_agc_calibrate_features_chain(campaign):
    tmp, src, dpath, tpath, truth, n = campaign
    runner = CliRunner()
    res = runner.invoke(cli, ["agc", str(src), "--targets", str(tpath), "--datasets", str(dpath),
                              "--out", str(tmp / "agc.parquet"), "--fit", str(tmp / "agc.json"),
                              "--plot", str(tmp / "cv.png")])
    assert res.exit_code == 0, res.output
    assert "agc: 2010_12_1: a = " in res.output and "b = 0.0" in res.output
    fit = json.loads((tmp / "agc.json").read_text())
    assert fit["b"] == pytest.approx(0.01, rel=0.05)

    res = runner.invoke(cli, ["calibrate", str(tmp / "agc.parquet"), "--targets", str(tpath), "--datasets", str(dpath),
                              "--out", str(tmp / "S.parquet"), "--json", str(tmp / "S.json"), "--plot", str(tmp / "S.png")])
    assert res.exit_code == 0, res.output
    assert "S(t) FWHM 7.2" in res.output
    cal = json.loads((tmp / "S.json").read_text())
    assert cal["fwhm_ns"] == pytest.approx(7.2, rel=0.02) and cal["b"] == pytest.approx(fit["b"])

    # features of the normalised table and of two "chunks" at once (the sim rule passes several files)
    half = pd.read_parquet(tmp / "agc.parquet")
    for k, part in enumerate((half.iloc[: n // 2], half.iloc[n // 2:])):
        part.to_parquet(tmp / f"chunk{k}.parquet", index=False)
    res = runner.invoke(cli, ["features", str(tmp / "agc.parquet"), "--calibration", str(tmp / "S.json"),
                              "--out", str(tmp / "f_real.parquet")])
    assert res.exit_code == 0, res.output
    assert f"features: {n} pulses" in res.output
    res = runner.invoke(cli, ["features", str(tmp / "chunk0.parquet"), str(tmp / "chunk1.parquet"),
                              "--calibration", str(tmp / "S.json"), "--out", str(tmp / "f_sim.parquet")])
    assert res.exit_code == 0, res.output
    real = pd.read_parquet(tmp / "f_real.parquet")
    both = pd.read_parquet(tmp / "f_sim.parquet")
    assert len(real) == n and both["pulse_id"].tolist() == real["pulse_id"].tolist()
    assert np.allclose(both["E"], real["E"]) and real["Apeak"].notna().all()
    # planar targets at the echo: AGC-normalised Apeak ~ S_peak * rho / (pi R^2)
    on = truth["target_index"] == 2  # tarp 0.41
    expect = SYSTEM.peak * 0.41 / np.pi / 1200.0**2
    assert np.median(real["Apeak"][on]) == pytest.approx(expect, rel=0.06)


def test_errors_are_one_clear_message(campaign, capsys):
    tmp, src, dpath, tpath, truth, n = campaign
    bad = tmp / "datasets_other.csv"
    bad.write_text("dataset,year,mean_range_m,pulse_width_fwhm_ns,footprint_diameter_m,sampling_ns\n"
                   "2012_10_1,2012,1200,7.2,0.18,1.0\n")
    with pytest.raises(SystemExit) as exc:
        main(["agc", str(src), "--targets", str(tpath), "--datasets", str(bad), "--out", str(tmp / "o.parquet"),
              "--fit", str(tmp / "o.json")])
    assert exc.value.code == 1
    err = capsys.readouterr().err
    assert "waveforest: error:" in err and "2010_12_1" in err and "not listed" in err
    assert not (tmp / "o.parquet").exists() and not (tmp / "o.json").exists()
    (tmp / "cal.json").write_text(json.dumps({"dataset": "2012_10_1", "noise_mean": 10.0, "noise_sd": 1.0}))
    with pytest.raises(SystemExit) as exc:
        main(["features", str(src), "--calibration", str(tmp / "cal.json"), "--out", str(tmp / "f.parquet")])
    assert exc.value.code == 1
    assert "no calibration JSON" in capsys.readouterr().err
    assert not (tmp / "f.parquet").exists()
