"""``waveforest ingest`` and ``waveforest info`` through click."""


import numpy as np
from click.testing import CliRunner
from fixtures.pulses import synthetic_pulses
from reference_io import RIEGL

from waveforest.cli import cli
from waveforest.io.las.write import write_waveform_las
from waveforest.io.pulses import read_pulses


def test_commands_are_registered():
    import click

    ctx = click.Context(cli)
    for name in ("ingest", "info"):
        cmd = cli.get_command(ctx, name)
        assert cmd is not None and cmd.name == name
    result = CliRunner().invoke(cli, ["ingest", "--help"])
    assert result.exit_code == 0 and "--trajectory" in result.output and "--nominal-range" in result.output


def test_ingest_with_trajectory_and_dataset(tmp_path):
    t = synthetic_pulses(300, seed=51, n_samples=(128, 256))
    las = write_waveform_las(tmp_path / "line_7.las", t, version="1.3", point_format=4)
    traj = tmp_path / "traj.csv"
    gps = t["gps_time"].to_numpy()
    sx, sy, sz = (t[f"sensor_{c}"].to_numpy() for c in "xyz")
    traj.write_text("gps_time,x,y,z\n" + "\n".join(f"{float(a)!r},{float(b)!r},{float(c)!r},{float(d)!r}" for a, b, c, d in zip(gps, sx, sy, sz)))
    out = tmp_path / "res" / "pulses.parquet"
    result = CliRunner().invoke(
        cli, ["ingest", str(las), "--out", str(out), "--dataset", "2010_12_1", "--trajectory", str(traj), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    assert result.output.count("\n") == 1 and "300 pulses" in result.output and "sensor trajectory" in result.output
    back = read_pulses(out)
    assert back.num_rows == 300 and set(back["dataset"].to_pylist()) == {"2010_12_1"}
    np.testing.assert_allclose(back["sensor_z"].to_numpy(), sz, atol=1e-6)
    assert back["samples"].to_pylist() == t["samples"].to_pylist()


def test_ingest_uses_config_agc_attribute(tmp_path):
    t = synthetic_pulses(40, seed=52)
    las = write_waveform_las(tmp_path / "x.las", t, agc_attribute="gain_code")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("agc:\n  attribute: gain_code\ningest:\n  chunk_points: 17\n")
    out = tmp_path / "p.parquet"
    result = CliRunner().invoke(cli, ["ingest", str(las), "--out", str(out), "--config", str(cfg), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "AGC from gain_code" in result.output
    np.testing.assert_array_equal(read_pulses(out)["agc"].to_numpy(), t["agc"].to_numpy())


def test_info_on_written_file(tmp_path):
    t = synthetic_pulses(120, seed=53, bits=16, n_samples=(60, 120))
    las = write_waveform_las(tmp_path / "y.las", t, bits=16, storage="external")
    result = CliRunner().invoke(cli, ["info", str(las)])
    assert result.exit_code == 0, result.output
    out = result.output
    n_echo = t["n_echoes"].to_numpy()
    assert "LAS version:           1.4" in out
    assert "point format:          9 (record length 59 bytes)" in out
    assert f"points:                {n_echo.sum():,}" in out
    assert "external: y.wdp" in out and "record header ok" in out
    assert "2 defined, 2 in use, 0 unused" in out
    assert f"pulses (GPS times):    {t.num_rows:,}" in out
    counts = np.bincount(np.concatenate([np.arange(1, k + 1) for k in n_echo]))[1:]
    assert "returns by number:     " + ", ".join(f"{i + 1}: {c:,}" for i, c in enumerate(counts)) in out
    lengths = np.array([len(s) for s in t["samples"].to_pylist()])
    assert f"60: {np.sum(lengths == 60):,} packets, 120: {np.sum(lengths == 120):,} packets" in out
    assert "AGC attribute:         user_data" in out


def test_info_summarises_the_real_riegl_file():
    result = CliRunner().invoke(cli, ["info", str(RIEGL)])
    assert result.exit_code == 0, result.output
    out = result.output
    for text in [
        "LAS version:           1.4",
        "generating software:   RiPROCESS 1.6.5.664",
        "point format:          9 (record length 63 bytes, extra bytes: Amplitude, Pulse width)",
        "points:                2,535",
        "global encoding:       4 (waveforms external)",
        "external: riegl_fwf.wdp (292,740 bytes, record header ok)",
        "100 defined, 2 in use, 98 unused (98 of them empty",
        "pulses (GPS times):    2,368",
        "packets:               2,375 (7 pulses with returns in several packets)",
        "returns by number:     1: 2,365, 2: 161, 3: 9",
        "AGC attribute:         none",
    ]:
        assert text in out, text
    # descriptor rows: index, bits, compression, samples, spacing
    rows = [ln.split() for ln in out.splitlines() if ln.startswith("      ")]
    assert [r[:5] for r in rows] == [["1", "16", "0", "60", "1000"], ["2", "16", "0", "120", "1000"]]
