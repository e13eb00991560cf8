"""``waveforest trace``: PLY in, sigma(t) table and plot out, clear errors."""

import json
import math
from dataclasses import replace

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest
from fixtures import scenes as syn

from waveforest import config
from waveforest.cli import main
from waveforest.mcrt import BeamSpec
from waveforest.scene import write_ply
from waveforest.sensor.reference import reference_sensor
from waveforest.settings import mcrt_setup, reference_system
from waveforest.stages.trace import SceneSpec, run


@pytest.fixture()
def plane_ply(tmp_path):
    return write_ply(syn.plane(6.0, 0.0, rho=0.3), tmp_path / "plane.ply")


def _run(args, capsys):
    with pytest.raises(SystemExit) as exc:
        main(args)
    return exc.value.code, capsys.readouterr()


def test_trace_plane_to_csv_and_plot(plane_ply, tmp_path, capsys):
    out, png = tmp_path / "sigma.csv", tmp_path / "sigma.png"
    try:
        main(["trace", str(plane_ply), "--out", str(out), "--rays", "2000", "--orders", "3",
              "--footprint", "0.3", "--scan-zenith", "10", "--plot", str(png), "--seed", "4"])
    except SystemExit as exc:  # click's standalone exit
        assert exc.code in (0, None)
    msg = capsys.readouterr().out
    assert f"wrote {out}" in msg and "2000 rays" in msg
    df = pd.read_csv(out)
    assert list(df.columns) == ["time_ns", "range_m", "sigma", "sigma_order_1", "sigma_order_2", "sigma_order_3"]
    assert df["sigma"].sum() == pytest.approx(0.3 * math.cos(math.radians(10)) / math.pi, rel=1e-5)
    np.testing.assert_allclose(np.diff(df["time_ns"]), 0.05, atol=1e-6)
    peak = df.loc[df["sigma"].idxmax(), "range_m"]
    assert peak == pytest.approx(1200.0, abs=0.02)  # default range to the target
    assert png.read_bytes()[:4] == b"\x89PNG"


def test_trace_parquet_carries_metadata(plane_ply, tmp_path):
    out = tmp_path / "sigma.parquet"
    cfg = config.load()
    mcrt = replace(mcrt_setup(cfg, n_rays=500, effects={"hotspot": 1.5}), max_order=2)
    scene = SceneSpec(path=plane_ply, species=None, height_m=None, ground_rho=0.3, lai_jitter=0.1)
    beam = BeamSpec(target=(0.0, 0.0, 0.0), range_m=800.0, scan_zenith_deg=0.0, azimuth_deg=0.0, divergence_mrad=0.2)
    sensor = reference_sensor(reference_system(cfg), range_m=800.0)
    res, _ = run(scene, beam, mcrt, out, seed=1, window_ns=cfg["mcrt"]["window_ns"], sensor=sensor)
    t = pq.read_table(out)
    meta = json.loads(t.schema.metadata[b"waveforest.trace"])
    assert meta["footprint_m"] == pytest.approx(0.16)
    assert meta["effects"] == {"hotspot": 1.5} and meta["n_rays"] == 500
    assert t.column("sigma").to_numpy().sum() == pytest.approx(res.sigma[0].sum())
    assert meta["t0_ns"] == pytest.approx(res.t0_ns[0])


@pytest.mark.parametrize(
    "extra,match",
    [
        (["--out", "x.txt"], "expected a .parquet or .csv"),
        (["--out", "x.csv", "--effect", "understory=1"], "not an MCRT effect"),
        (["--out", "x.csv", "--effect", "specular"], "NAME=VALUE"),
        (["--out", "x.csv", "--footprint", "0.2", "--divergence", "0.1"], "not both"),
        (["--out", "x.csv", "--rays", "0"], "'--rays'"),
        (["--out", "x.csv", "--range", "-100"], "'--range'"),
    ],
)
def test_trace_bad_options(plane_ply, tmp_path, capsys, extra, match):
    """Content errors exit 1, usage errors (an option's value out of range) exit 2; both name
    what was typed and leave nothing behind."""
    extra = [str(tmp_path / e) if e.startswith("x.") else e for e in extra]
    code, cap = _run(["trace", str(plane_ply), *extra], capsys)
    assert code == (2 if match.startswith("'--") else 1)
    assert match in cap.err and cap.err.startswith("waveforest: error:")
    assert not list(tmp_path.glob("x.*"))  # nothing half-written


def test_trace_bad_scene_files(tmp_path, capsys):
    code, cap = _run(["trace", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "s.csv")], capsys)
    assert code == 2 and "does not exist" in cap.err
    bad = tmp_path / "bad.ply"
    bad.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                   "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                   "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    code, cap = _run(["trace", str(bad), "--out", str(tmp_path / "s.csv")], capsys)
    assert code == 1 and "rho, tau, kind" in cap.err
    code, cap = _run(["trace", "--out", str(tmp_path / "s.csv")], capsys)
    assert code == 1 and "give a scene PLY file or --species (with --height)" in cap.err
    assert not (tmp_path / "s.csv").exists()


def test_trace_existing_output_survives_a_failure(plane_ply, tmp_path, capsys):
    out = tmp_path / "s.csv"
    out.write_text("keep me")
    code, _ = _run(["trace", str(plane_ply), "--out", str(out), "--effect", "understory=1"], capsys)
    assert code == 1 and out.read_text() == "keep me"


def test_trace_species_equals_the_same_scene_as_ply(tmp_path, capsys):
    """``--species S --height H --seed K`` traces build_scene(S, H, K): same sigma as its PLY."""
    from waveforest.vegetation import build_scene

    ply = write_ply(build_scene("raspberry", 1.0, 3), tmp_path / "rasp.ply")
    args = ["--out", None, "--rays", "400", "--orders", "4", "--seed", "3", "--scan-zenith", "8"]
    outs = []
    for name, scene_args in (("species.csv", ["--species", "raspberry", "--height", "1.0"]), ("ply.csv", [str(ply)])):
        a = list(args)
        a[1] = str(tmp_path / name)
        try:
            main(["trace", *scene_args, *a])
        except SystemExit as exc:
            assert exc.code in (0, None)
        outs.append(pd.read_csv(tmp_path / name))
    assert "wrote" in capsys.readouterr().out
    a, b = outs
    assert a["sigma"].sum() > 0.05  # a real canopy return
    np.testing.assert_allclose(a["sigma"], b["sigma"], rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(a["time_ns"], b["time_ns"], rtol=0, atol=1e-6)
    code, cap = _run(["trace", "--species", "raspberry", "--out", str(tmp_path / "x.csv")], capsys)
    assert code == 1 and "--height" in cap.err


def test_trace_takes_the_sampler_and_roulette_from_the_config(plane_ply, tmp_path):
    """mcrt.sampler and mcrt.roulette reach the tracer: on a plane every estimator is exact, and
    the written metadata names the estimator used."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("mcrt: {sampler: sobol, roulette: 0.5}\n")
    out = tmp_path / "sigma.parquet"
    try:
        main(["trace", str(plane_ply), "--out", str(out), "--rays", "1024", "--orders", "3", "--config", str(cfg)])
    except SystemExit as exc:
        assert exc.code in (0, None)
    t = pq.read_table(out)
    meta = json.loads(t.schema.metadata[b"waveforest.trace"])
    assert meta["sampler"] == "sobol" and meta["roulette"] == 0.5
    assert t.column("sigma").to_numpy().sum() == pytest.approx(0.3 / math.pi, rel=1e-5)


def test_trace_holds_the_plant_while_the_seed_varies_the_rays(tmp_path, capsys):
    """--plant-seed fixes the --species instance: two ray seeds trace the same plant (same first
    hits of the scene's elements up to Monte Carlo noise, same time grid), and the same seeds
    give the same file; --height or --plant-seed with a PLY file is an error."""
    outs = []
    for seed in (1, 2, 1):
        out = tmp_path / f"s{seed}_{len(outs)}.parquet"
        try:
            main(["trace", "--species", "birch", "--height", "3", "--plant-seed", "7", "--rays", "2048",
                  "--orders", "2", "--seed", str(seed), "--out", str(out)])
        except SystemExit as exc:
            assert exc.code in (0, None)
        outs.append(pq.read_table(out))
    meta = [json.loads(t.schema.metadata[b"waveforest.trace"]) for t in outs]
    assert [m["plant_seed"] for m in meta] == [7, 7, 7] and meta[0]["t0_ns"] == meta[1]["t0_ns"]
    assert outs[0].equals(outs[2]) and not outs[0].equals(outs[1])
    s0, s1 = (t.column("sigma").to_numpy().sum() for t in outs[:2])
    assert s0 > 0.05 and abs(s0 / s1 - 1) < 0.05  # one plant, two ray streams
    plane = write_ply(syn.plane(6.0, 0.0, rho=0.3), tmp_path / "plane.ply")
    code, cap = _run(["trace", str(plane), "--plant-seed", "3", "--out", str(tmp_path / "x.csv")], capsys)
    assert code == 1 and "--plant-seed build a --species instance" in cap.err


def test_trace_reports_the_recorded_waveform_its_features_and_the_budget(plane_ply, tmp_path, capsys):
    """A plane at the reference sensor's range: the noise-free waveform peaks at plane_dn x
    rho / plane_hdrf (Eq. 7), Apeak and E on stdout and in the metadata agree with it; the
    adaptive budget's estimated error is written and a budget capped above its tolerance warns."""
    cfg = config.load()
    ref = cfg["sensitivity"]["reference_system"]
    out, wave = tmp_path / "s.parquet", tmp_path / "w.csv"
    try:
        main(["trace", str(plane_ply), "--out", str(out), "--waveform", str(wave), "--tolerance", "0.2"])
    except SystemExit as exc:
        assert exc.code in (0, None)
    msg = capsys.readouterr().out
    meta = json.loads(pq.read_table(out).schema.metadata[b"waveforest.trace"])
    w = pd.read_csv(wave)
    peak = ref["plane_dn"] * 0.3 / ref["plane_hdrf"]
    assert w["waveform_dn"].max() == pytest.approx(peak, rel=0.01)
    assert meta["features"]["Apeak"] == pytest.approx(peak, rel=0.02)
    assert "adaptive, tolerance 0.2, estimated error" in msg and "Apeak" in msg
    assert 0 <= meta["mc_error_noise_sd"] <= 0.2
    small = tmp_path / "c.yaml"
    small.write_text("mcrt: {min_rays: 1024, max_rays: 2048}\n")
    err = _ok(["trace", "--species", "fireweed", "--height", "1", "--orders", "3", "--tolerance", "0.001",
               "--config", str(small), "--out", str(tmp_path / "t.csv")], capsys)
    assert "stopped at mcrt.max_rays (2048) with an estimated error of" in err
    err = _ok(["trace", str(plane_ply), "--out", str(tmp_path / "m.csv"), "--rays", "64", "--target-x", "500"], capsys)
    assert "the beam met nothing" in err


def _ok(args, capsys) -> str:
    """Run a command that succeeds; its stderr."""
    try:
        main(args)
    except SystemExit as exc:
        assert exc.code in (0, None)
    return capsys.readouterr().err
