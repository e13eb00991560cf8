"""simulate: geometry against an analytic scene, determinism, chunk independence, effects."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pyarrow as pa
import pytest
from fixtures.tables import plate_scene, pulse_table
from scipy.special import erf

from waveforest import config
from waveforest.constants import RANGE_PER_NS
from waveforest.io.pulses import same_table
from waveforest.model.forward import noise_free_waveform, noise_free_waveforms, render_sigma, split_effects
from waveforest.model.simulate import plan, simulate_pulses
from waveforest.sensor import feature_table, gaussian_system_waveform
from waveforest.sensor.calibration import Calibration, load_calibration
from waveforest.settings import sensor_setup, simulate_settings

SAMPLES = {  # sample_id: species, x, y, ground_z, height
    "R1": ("raspberry", 100.0, 200.0, 50.0, 1.2),
    "F1": ("fireweed", 110.0, 200.0, 51.0, 0.9),
    "B1": ("birch", 120.0, 200.0, 52.0, 3.0),
    "P1": ("scots_pine", 130.0, 200.0, 52.0, 3.0),  # not a modelled species
}
ALTITUDE = 1000.0
S_PEAK = 7.0e8  # DN m^2 per unit sigma: a 0.47 plate at 1000 m peaks at ~105 DN (no clipping)


def _selected(n_per_sample=6, seed=0):
    rng = np.random.default_rng(seed)
    echoes, meta = [], []
    for sid, (sp, x, y, gz, h) in SAMPLES.items():
        for _ in range(n_per_sample):
            dx, dy = rng.uniform(-0.3, 0.3, 2)
            echoes.append([(x + dx, y + dy, gz + h)])
            meta.append((sid, sp, x, y, gz, h))
    df = pulse_table("2010_12_1", echoes, pulse_ids=np.arange(len(echoes)) * 7 + 3).to_pandas()
    zen, az = np.radians(rng.uniform(0, 15, len(df))), rng.uniform(0, 2 * np.pi, len(df))
    d = np.column_stack([np.sin(zen) * np.cos(az), np.sin(zen) * np.sin(az), -np.cos(zen)])
    echo = np.array([e[0] for e in echoes])
    sensor = echo - d * (ALTITUDE / np.cos(zen))[:, None]
    df[["dir_x", "dir_y", "dir_z"]] = d
    df[["sensor_x", "sensor_y", "sensor_z"]] = sensor
    m = pd.DataFrame(meta, columns=["sample_id", "species", "sample_x", "sample_y", "ground_z", "height_m"])
    for c in m.columns:
        df[c] = m[c].to_numpy()
    df["functional_group"] = "x"
    df["is_tree"] = df["species"].isin(["birch", "scots_pine"])
    df["comparison_set"] = df["species"].isin(["birch", "raspberry", "fireweed"])
    df["classification_set"] = True
    return pa.Table.from_pandas(df, preserve_index=False)


def _info():
    return pd.Series(dict(dataset="2010_12_1", year=2010, mean_range_m=ALTITUDE, pulse_width_fwhm_ns=7.2,
                          footprint_diameter_m=0.15, divergence_mrad=0.15, sampling_ns=1.0))


def _cfg(**simulate):
    return config.load(overrides={"seed": 5, "mcrt": {"n_rays": 200, "max_order": 3},
                                  "simulate": dict({"instances_per_sample": 2}, **simulate)})


def _cal():
    return Calibration(gaussian_system_waveform(7.2, S_PEAK), 10.0, 1.5)


def _sim(cfg, chunk=0, chunks=1, effects=None, builder=plate_scene, threads=None):
    table, summary = simulate_pulses(_selected(), _info(), _cal(), simulate_settings(cfg), chunk=chunk,
                                     chunks=chunks, effects=effects, progress=False, scene_builder=builder,
                                     threads=threads)
    return table, summary


def _sorted(t: pa.Table) -> pa.Table:
    return t.sort_by("pulse_id")


_same = same_table


def test_plate_geometry_and_amplitude():
    cfg = _cfg()
    table, s = _sim(cfg)
    df = table.to_pandas()
    sel = _selected().to_pandas()
    assert s.n_pulses == 18 and s.n_written == 18 and s.n_no_echo == 0
    assert set(df["pulse_id"]) == set(sel.loc[sel["comparison_set"], "pulse_id"])
    assert (df["source"] == "sim").all() and set(df["sim_instance"]) <= {0, 1}
    merged = df.merge(sel[["pulse_id", "sensor_x", "sensor_y", "sensor_z"]], on="pulse_id", suffixes=("", "_real"))
    assert np.allclose(merged[["sensor_x", "sensor_y", "sensor_z"]].to_numpy(),
                       merged[["sensor_x_real", "sensor_y_real", "sensor_z_real"]].to_numpy())
    ez = np.array([z[0] for z in df["echo_z"]])
    # first CFD echo on the plate top: H = field height (CFD + sampling error << 5 cm)
    assert np.abs(ez - df["ground_z"] - df["height_m"]).max() < 0.05
    # echo positions lie on the recorded beam line
    ex, ey = np.array([x[0] for x in df["echo_x"]]), np.array([y[0] for y in df["echo_y"]])
    along = (df["sensor_z"] - ez) / -df["dir_z"]
    assert np.allclose(ex, df["sensor_x"] + df["dir_x"] * along, atol=1e-6)
    assert np.allclose(ey, df["sensor_y"] + df["dir_y"] * along, atol=1e-6)
    # anchor and echo time agree with the range of the first echo
    t0 = np.array([t[0] for t in df["echo_time_ns"]])
    assert np.allclose(df["range_m"], np.hypot(np.hypot(df["anchor_x"] - df["sensor_x"], df["anchor_y"] - df["sensor_y"]),
                                               df["anchor_z"] - df["sensor_z"]) + t0 * RANGE_PER_NS, atol=1e-6)
    # Eq. 7 amplitude: sigma = rho cos(theta)/pi per unit power seen at the slant, R = range to ground
    f = feature_table(table, {"2010_12_1": dict(noise_mean=10.0, noise_sd=1.5)})
    cos = -df["dir_z"].to_numpy()
    r = (df["sensor_z"] - df["ground_z"]).to_numpy() / cos
    expected = S_PEAK * 0.47 * cos / np.pi / r**2
    assert np.allclose(df["sigma_total"], 0.47 * cos / np.pi, rtol=1e-6)
    assert np.abs(f["Apeak"].to_numpy() / expected - 1).max() < 0.05  # sampling phase + noise + rounding


def test_twins_are_recorded_at_the_real_pulses_agc_gain():
    """A twin is recorded at its real pulse's AGC gain g and normalised like it (Eq. 1): the
    normalised noise has SD sqrt(sd^2 + 1/12) / g (analog noise and rounding, not gained by
    the AGC), the signal is that of gain 1, and g = 1 changes nothing."""
    cfg, g = _cfg(), 0.5
    sel = _selected(n_per_sample=60)

    def run(gain):
        t = sel if gain is None else sel.append_column("agc_gain", pa.array(np.full(sel.num_rows, gain)))
        out, _ = simulate_pulses(t, _info(), _cal(), simulate_settings(cfg), progress=False,
                                 scene_builder=plate_scene)
        return out.sort_by("pulse_id")

    plain, ones, gained = run(None), run(1.0), run(g)
    assert _same(plain, ones)
    cal = _cal()

    def pre_echo(t):  # the record starts 3.3-4.8 m of range (>= 22 ns) before the echo
        return np.array([s[:15] for s in t.column("samples").to_pylist()], dtype=float)

    expected_sd = np.sqrt(cal.noise_sd**2 + 1 / 12) / g
    assert abs(pre_echo(gained).std(ddof=1) / expected_sd - 1) < 0.06
    assert abs(pre_echo(plain).std(ddof=1) / (expected_sd * g) - 1) < 0.06
    assert abs(pre_echo(gained).mean() - cal.noise_mean) < 0.1
    noise = {"2010_12_1": dict(noise_mean=cal.noise_mean, noise_sd=cal.noise_sd)}
    a_plain = feature_table(plain, noise)["Apeak"].mean()
    a_gained = feature_table(gained, noise)["Apeak"].mean()
    assert abs(a_gained / a_plain - 1) < 0.02  # ~105 DN, noise SD 3 DN over 180 pulses


def test_a_twin_at_low_gain_arms_on_the_recorded_noise():
    """The DR circuits see the recorded signal: at gain g the normalised noise has SD sd / g, and
    a CFD armed at 4 sd instead of 4 sd / g fires on it. With correlated noise (lag-1 0.6) and
    g = 0.5 that put 6 % of first echoes > 5 ns before a plane's echo; armed on the recorded
    noise, 0.3 %, as at g = 1 (0.1 %)."""
    cfg, cal, n, r = _cfg(), _cal(), 3000, 1000.0
    setup = sensor_setup(cfg, cal.system, cal.noise_mean, cal.noise_sd, 1.0,
                         render_effects={"noise_autocorr": 0.6})
    sigma = np.zeros((n, 400))
    sigma[:, 200] = 0.02  # a plane 10 ns into the profile: ~15 DN at gain 1
    t0 = np.full(n, r / RANGE_PER_NS - 10.0)  # two-way time of bin 0, ns

    def early(g):
        p = render_sigma(sigma, t0, np.full(n, r), setup, np.random.default_rng(1), gain=np.full(n, g))
        t = p.echo_times_ns[:, 0] + p.first_sample_ns
        return np.mean(t < np.nanmedian(t) - 5.0)

    assert early(0.5) < 0.01 and early(1.0) < 0.01


def test_same_seed_same_table_and_chunks_do_not_matter():
    cfg = _cfg()
    a, _ = _sim(cfg)
    b, _ = _sim(cfg)
    assert _same(a, b)
    parts = [_sim(cfg, chunk=c, chunks=3)[0] for c in range(3)]
    assert sum(p.num_rows for p in parts) == a.num_rows
    assert _same(_sorted(pa.concat_tables(parts)), _sorted(a))
    c, _ = _sim(_cfg() | {"seed": 6})
    assert not _sorted(c).column("samples").equals(_sorted(a).column("samples"))


def test_worker_threads_do_not_change_the_table():
    """Groups shared over worker threads (finishing in any order) give the serial table, row for row."""
    cfg = _cfg()
    serial, _ = _sim(cfg, threads=1)
    assert serial.num_rows > 4
    assert _same(_sim(cfg, threads=2)[0], serial)
    assert _same(_sim(cfg, threads=3)[0], serial)


def _birch_samples(n_samples: int, per_sample: int) -> pa.Table:
    """``per_sample`` identical nadir pulses over each of ``n_samples`` 3-m birch samples (0.4 m
    east of the stem, 1.5 m up): their features differ only by the plant instance and noise."""
    n = n_samples * per_sample
    k = np.repeat(np.arange(n_samples), per_sample)
    x, y, gz, h = 1000.0 + 20.0 * k, np.full(n, 500.0), np.full(n, 40.0), np.full(n, 3.0)
    df = pulse_table("2010_12_1", [[(xi + 0.4, yi, zi + 1.5)] for xi, yi, zi in zip(x, y, gz)],
                     pulse_ids=np.arange(n) * 5 + 1).to_pandas()
    df[["dir_x", "dir_y", "dir_z"]] = [0.0, 0.0, -1.0]
    df["sensor_x"], df["sensor_y"], df["sensor_z"] = x + 0.4, y, gz + ALTITUDE
    for c, v in (("sample_id", [f"B{i}" for i in k]), ("species", "birch"), ("sample_x", x), ("sample_y", y),
                 ("ground_z", gz), ("height_m", h), ("functional_group", "broadleaf"), ("is_tree", True),
                 ("comparison_set", True), ("classification_set", True)):
        df[c] = v
    return pa.Table.from_pandas(df, preserve_index=False)


@pytest.mark.parametrize("pool", [2, 1])
def test_an_instance_pool_keeps_the_between_instance_variance_of_a_new_instance_per_pulse(pool):
    """Identical beams over many samples: the spread of sigma_total is the vegetation's
    between-instance variance. A pool of 1 or 2 instances per sample (5 pulses each) must give
    the spread and mean of the paper's rule (an instance per pulse); reusing one plant
    everywhere would collapse the spread to the Monte Carlo noise, which the pulses sharing an
    instance measure."""
    n_samples = 40
    sel = _birch_samples(n_samples, 5)
    runs = {}
    for k in (None, pool):
        cfg = config.load(overrides={"seed": 9, "mcrt": {"n_rays": 400, "max_order": 3},
                                     "simulate": {"instances_per_sample": k, "max_pulses": None}})
        t, _ = simulate_pulses(sel, _info(), _cal(), simulate_settings(cfg), progress=False)
        runs[k] = t.select(["sample_id", "sim_instance", "sigma_total"]).to_pandas()
    fresh, pooled = runs[None]["sigma_total"], runs[pool]
    assert len(fresh) >= 190 and len(pooled) >= 190
    assert pooled.groupby("sample_id")["sim_instance"].nunique().max() == pool
    ratio = pooled["sigma_total"].var() / fresh.var()
    assert 0.5 < ratio < 2.0, ratio
    se = np.sqrt(fresh.var() / len(fresh) + pooled["sigma_total"].var() / (pool * n_samples))
    assert abs(pooled["sigma_total"].mean() - fresh.mean()) < 4 * se
    # the test's power: pulses sharing an instance differ only by Monte Carlo noise
    mc = pooled.groupby(["sample_id", "sim_instance"])["sigma_total"].var().mean()
    assert mc < 0.1 * fresh.var()


def test_plan_cap_and_instances():
    sel = _selected().to_pandas()
    cfg = _cfg(max_pulses=4)
    p = plan(sel, simulate_settings(cfg), "2010_12_1")
    assert p.groupby("species").size().to_dict() == {"birch": 4, "fireweed": 4, "raspberry": 4}
    assert set(p["instance"]) <= {0, 1} and (p["chunk_hash"] >= 0).all()
    # the same pulses whatever the chunking; the groups are whole in a chunk
    for _chunks in (2, 3):
        assert (p.groupby("group")["chunk_hash"].nunique() == 1).all()
    one = plan(sel, simulate_settings(_cfg(instances_per_sample=None)), "2010_12_1")
    assert one["group"].nunique() == len(one)  # the paper's rule: an instance per pulse


def test_builder_sees_the_vegetation_effects_and_pool_size():
    calls = []

    def recording(species, height, seed, **kw):
        calls.append((species, height, seed, kw))
        return plate_scene(species, height, seed, **kw)

    cfg = _cfg()
    _sim(cfg, effects={"understory": 1.5, "hotspot": 1.3, "noise_autocorr": 0.5}, builder=recording)
    assert len(calls) == len({(c[0], c[2]) for c in calls}) <= 3 * 2  # one build per (sample, instance)
    assert all(c[3]["understory"] == 1.5 and "hotspot" not in c[3] for c in calls)
    assert all(c[3]["ground_rho"] == 0.30 and c[3]["lai_jitter"] == 0.10 for c in calls)
    veg, mcrt, sensor, xy = split_effects({"understory": 1.5, "hotspot": 1.3, "noise_autocorr": 0.5, "xy_error": 0.2})
    assert veg == {"understory": 1.5} and mcrt == {"hotspot": 1.3} and sensor == {"noise_autocorr": 0.5}
    assert xy == 0.2


def _half_plate(species, height, seed, **kw):
    """The fixture's plate cut to x > 0 of the sample (local frame); the ground stays whole."""
    from waveforest.scene import Scene

    sc = plate_scene(species, height, seed, **kw)
    tri = sc.triangles.copy()
    top = tri[:, 0, 2] > 0.01
    tri[top, :, 0] = np.clip(tri[top, :, 0], 0.0, None)
    return Scene(tri, sc.rho, sc.tau, sc.kind)


def _first_echo_h(table: pa.Table) -> pd.Series:
    """Height of each twin's first echo above the ground, m, by pulse_id."""
    d = table.to_pandas().set_index("pulse_id")
    return pd.Series([z[0] for z in d["echo_z"]], d.index) - d["ground_z"]


def test_xy_error_moves_the_traced_beam_not_the_record():
    """A plate covering only x > 0 of each sample: a large xy_error makes some pulses miss it."""
    cfg = _cfg()
    base, _ = _sim(cfg, builder=_half_plate)
    moved, _ = _sim(cfg, effects={"xy_error": 1.0}, builder=_half_plate)
    b, m = base.to_pandas().set_index("pulse_id"), moved.to_pandas().set_index("pulse_id")
    common = b.index.intersection(m.index)
    assert len(common) >= 12
    changed = np.abs(_first_echo_h(base)[common] - _first_echo_h(moved)[common]) > 0.3  # plate top vs ground
    assert changed.sum() >= 2
    for col in ("sensor_x", "sensor_y", "dir_x", "dir_y"):  # recorded geometry unchanged
        assert np.array_equal(b.loc[common, col], m.loc[common, col])
    # echoes stay on the recorded beam line
    ez = np.array([z[0] for z in m.loc[common, "echo_z"]])
    ex = np.array([x[0] for x in m.loc[common, "echo_x"]])
    along = (m.loc[common, "sensor_z"] - ez) / -m.loc[common, "dir_z"]
    assert np.allclose(ex, m.loc[common, "sensor_x"] + m.loc[common, "dir_x"] * along, atol=1e-6)


def test_georeferencing_drift_is_a_unit_gauss_markov_process_in_gps_time():
    """georeferencing_drift: N(0, 1) per pulse and axis, corr exp(-dt / tau) between two pulses,
    and each pulse's value independent of the order the pulses come in."""
    from waveforest.model.forward import GEOREF_TAU_S, georeferencing_drift

    rng = np.random.default_rng(4)
    m = 1_000  # independent pairs (t0, t0 + dt): pairs 1e6 tau apart, so corr exp(-1e6) = 0 between them
    for dt, rho in ((0.05, np.exp(-0.05 / GEOREF_TAU_S)), (GEOREF_TAU_S, np.exp(-1.0)), (100.0, np.exp(-10.0))):
        t0 = 1e6 * GEOREF_TAU_S * np.arange(m)
        x = georeferencing_drift(rng.standard_normal((2 * m, 2)), np.concatenate([t0, t0 + dt]))
        first, second = x[:m].ravel(), x[m:].ravel()
        se = 1.0 / np.sqrt(first.size)
        assert abs(first.std() - 1.0) < 4 * se and abs(second.std() - 1.0) < 4 * se
        assert abs(np.corrcoef(first, second)[0, 1] - rho) < 4 * se
    z, t = rng.standard_normal((50, 2)), rng.uniform(0.0, 60.0, 50)
    order = rng.permutation(50)
    np.testing.assert_allclose(georeferencing_drift(z[order], t[order]), georeferencing_drift(z, t)[order])
    t[3] = np.nan  # a pulse without a GPS time gets its own draw
    assert np.isfinite(georeferencing_drift(z, t)).all() and (georeferencing_drift(z, t)[3] == z[3]).all()


def test_drift_dof_counts_the_independent_values_a_drift_holds():
    """drift_dof: n pulses at one instant hold 1 value, pulses far apart n, groups add up; and
    on a pass of pulses over 40 s the mean square of the simulated drift has the variance of
    chi^2_nu / nu (Monte Carlo over 4000 drifts, 2 axes each)."""
    from waveforest.model.forward import GEOREF_TAU_S, drift_dof, georeferencing_drift

    assert drift_dof(np.zeros(7), np.zeros(7)) == pytest.approx(1.0)
    assert drift_dof(1e6 * np.arange(7.0), np.zeros(7)) == pytest.approx(7.0)
    assert drift_dof(np.zeros(6), np.repeat([0, 1, 2], 2)) == pytest.approx(3.0)  # three datasets
    assert drift_dof(np.array([0.0, np.nan, np.nan]), np.zeros(3)) == pytest.approx(3.0)
    rng = np.random.default_rng(5)
    t = np.sort(rng.uniform(0.0, 4 * GEOREF_TAU_S, 300))
    nu = drift_dof(t, np.zeros(t.size))
    assert 3.0 < nu < 8.0  # four correlation times
    ms = np.array([np.mean(georeferencing_drift(rng.standard_normal((t.size, 2)), t) ** 2, axis=0)
                   for _ in range(2000)]).ravel()
    assert ms.mean() == pytest.approx(1.0, abs=0.05)
    assert ms.var() == pytest.approx(2.0 / nu, rel=0.15)  # the SE of a variance from 4000 draws ~ 5 %


def test_xy_error_moves_the_pulses_of_one_pass_together():
    """A georeferencing error wanders over seconds: the twins of one sample (one plant, one
    (sample, instance) group), recorded within a few ms, share nearly one offset c. On the half
    plate (x > 0) a twin then hits iff its own x offset from the stem dx > -c_x, so within a
    sample the hits are exactly the largest dx; independent offsets per pulse (SD 0.5 m against
    dx within +-0.3 m) would break that order."""
    df = _selected(n_per_sample=12).to_pandas()
    k = pd.factorize(df["sample_id"])[0]
    df["gps_time"] = 40.0 * k + 1e-3 * df.groupby("sample_id").cumcount()  # passes 40 s apart
    sel = pa.Table.from_pandas(df, preserve_index=False)
    table, _ = simulate_pulses(sel, _info(), _cal(), simulate_settings(_cfg(instances_per_sample=1)),
                               effects={"xy_error": 0.5}, progress=False, scene_builder=_half_plate)
    hit = _first_echo_h(table) > 0.3
    d = df.set_index("pulse_id").loc[hit.index]
    dx = [e[0] for e in d["echo_x"]] - d["sample_x"]
    mixed = 0
    for _, g in pd.DataFrame({"s": d["sample_id"], "dx": dx, "hit": hit}).groupby("s"):
        g = g.sort_values("dx")
        assert (np.diff(g["hit"].to_numpy().astype(int)) >= 0).all()  # misses, then hits
        mixed += 0 < g["hit"].sum() < len(g)
    assert mixed >= 1 and len(hit) == 36  # 3 compared samples x 12 pulses


def test_load_calibration(tmp_path):
    sw = gaussian_system_waveform(7.2, S_PEAK)
    sw.save(tmp_path / "s.parquet")
    (tmp_path / "s.json").write_text(json.dumps(dict(dataset="d", noise_mean=9.5, noise_sd=1.25)))
    cal = load_calibration(tmp_path / "s.json", tmp_path / "s.parquet")
    assert (cal.noise_mean, cal.noise_sd, cal.range_correction) == (9.5, 1.25, None)
    assert cal.system.fwhm_ns == pytest.approx(7.2, rel=1e-3)
    (tmp_path / "bad.json").write_text(json.dumps(dict(dataset="d", noise_mean=9.5)))
    with pytest.raises(ValueError, match="noise_sd"):
        load_calibration(tmp_path / "bad.json", tmp_path / "s.parquet")


def test_cli_end_to_end_with_the_vegetation_models(tmp_path):
    """Files in, files out, with the real vegetation models (few rays, one pulse per species)."""
    from waveforest.cli import main
    from waveforest.io.pulses import read_pulses, write_pulses

    veg = pytest.importorskip("waveforest.vegetation")
    if not hasattr(veg, "build_scene"):
        pytest.skip("waveforest.vegetation.build_scene not available yet")
    sel = _selected().drop_columns(["sample_x", "sample_y", "height_m"])  # supplied by --fields
    write_pulses(sel, tmp_path / "sel.parquet")
    group = {"birch": "broadleaf", "scots_pine": "conifer"}  # the others of SAMPLES are low_green
    rows = [dict(sample_id=k, year=2010, species=v[0], functional_group=group.get(v[0], "low_green"), x=v[1], y=v[2],
                 ground_z=v[3], height_m=v[4], radius_m=0.5, is_tree=int(v[0] in ("birch", "scots_pine"))) for k, v in SAMPLES.items()]
    pd.DataFrame(rows).to_csv(tmp_path / "fields.csv", index=False)
    pd.DataFrame([_info().to_dict()]).to_csv(tmp_path / "datasets.csv", index=False)
    gaussian_system_waveform(7.2, S_PEAK).save(tmp_path / "s.parquet")
    (tmp_path / "s.json").write_text(json.dumps(dict(dataset="2010_12_1", noise_mean=10.0, noise_sd=1.5)))
    (tmp_path / "c.yaml").write_text("mcrt: {n_rays: 300, max_order: 3}\nsimulate: {max_pulses: 1, instances_per_sample: 1}\n")
    args = ["simulate", str(tmp_path / "sel.parquet"), "--fields", str(tmp_path / "fields.csv"), "--datasets",
            str(tmp_path / "datasets.csv"), "--system", str(tmp_path / "s.parquet"), "--calibration",
            str(tmp_path / "s.json"), "--chunks", "1", "--out", str(tmp_path / "sim.parquet"),
            "--config", str(tmp_path / "c.yaml")]
    main(args)
    out = read_pulses(tmp_path / "sim.parquet")
    assert 1 <= out.num_rows <= 3 and set(out.column("source").to_pylist()) == {"sim"}
    h = np.array([z[0] for z in out.column("echo_z").to_pylist()]) - out.column("ground_z").to_numpy()
    assert np.all((h > -0.3) & (h < out.column("height_m").to_numpy() + 0.3))  # within the plant or on the ground


def test_noise_free_waveforms_take_the_first_echo_not_the_strongest():
    """Two delta returns 20 ns apart (separate segments at 3 noise SDs), the later three times the
    earlier: Apeak is the first's (S(t)'s peak x sigma / R^2), E its Gaussian area; a pulse below
    the segment level has none; one pulse of the batch through noise_free_waveform gives the same."""
    bin_ns, r_m, fwhm = 0.05, 1000.0, 7.2
    system = gaussian_system_waveform(fwhm, S_PEAK)
    sigma = np.zeros((3, 2000))
    sigma[0, 600], sigma[0, 1000] = 0.1, 0.3  # per-bin sums
    sigma[1, 600] = 1e-6  # far below 3 noise SDs
    sigma[2, 800] = 0.2
    t_first, v, w, f = noise_free_waveforms(sigma, np.zeros(3), bin_ns, system, 1.3, r_m)
    peak = S_PEAK / r_m**2 * np.array([0.1, np.nan, 0.2])  # DN at the return's time
    inside = erf(np.sqrt(np.log(peak / (3 * 1.3))))  # the Gaussian's share above the segment level
    area = peak * fwhm / (2 * np.sqrt(2 * np.log(2))) * np.sqrt(2 * np.pi) * inside
    assert f["Apeak"] == pytest.approx(peak, rel=0.01, nan_ok=True)
    assert f["E"] == pytest.approx(area, rel=0.01, nan_ok=True)
    assert f["FWHM"] == pytest.approx([fwhm, np.nan, fwhm], abs=0.1, nan_ok=True)
    one = noise_free_waveform(SimpleNamespace(sigma=sigma, t0_ns=np.zeros(3), bin_ns=bin_ns), system, 1.3, r_m, 2)
    assert one[2]["Apeak"] == pytest.approx(f["Apeak"][2]) and np.allclose(one[1], v[2])
