"""Recording one dataset: AGC loop, sensor, geometry errors and the LAS pulse table (no MCRT needed)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from waveforest.campaign.flight import plan_flight, site_pulses
from waveforest.campaign.layout import area_frame
from waveforest.campaign.params import load_datasets, load_layout
from waveforest.campaign.synthesize import record_dataset, resolve_effects
from waveforest.campaign.truth_sensor import TruthSensor
from waveforest.constants import BIN_NS, C_M_PER_NS, RANGE_PER_NS

pytest.importorskip("waveforest.io.las.write")


def _planar_dataset(tmp_path, xy_error=0.0):
    row = load_datasets(["2012_10_1"]).iloc[0]
    lay = load_layout()
    frame = area_frame(lay)
    sites = pd.DataFrame({"site": ["plane"], "s": [10.0], "w": [-30.0], "ground_z": [150.0], "disc_m": [4.0]})
    plan = plan_flight(row, frame, lay, 1.0, 5, 150.0)
    p = site_pulses(plan, sites, lay, 5)
    p["kind"] = "target"
    n = len(p)
    r = p["range_ground_m"].to_numpy()
    sigma = np.zeros((n, 300))
    sigma[:, 100] = 0.3 / np.pi * -p["dir_z"].to_numpy()
    sigma[1::2] = 0.0  # every second pulse returns nothing: no DR echo, not recorded
    t0 = 2 * r / C_M_PER_NS - 100.5 * BIN_NS
    sensor = TruthSensor.from_row(row)
    a0 = np.zeros(n)
    rows = np.arange(n)
    eff = resolve_effects({"xy_error": xy_error})
    table, info, truth = record_dataset(row, sensor, plan, p, a0, [("plane", rows, sigma, t0, r)], eff, 5, lay,
                                         tmp_path, None)
    return p, sensor, table, info, truth


def test_pulse_table_geometry_and_dropped_pulses(tmp_path):
    p, sensor, table, info, truth = _planar_dataset(tmp_path)
    n = len(p)
    assert table.num_rows == info["n_pulses"] == (n + 1) // 2
    assert info["n_without_echo"] == n // 2
    assert (tmp_path / "2012_10_1.las").exists() and (tmp_path / "2012_10_1_trajectory.csv").exists()
    kept = p.iloc[::2]
    # first echo on the plane: the true ground point plus the range walk and jitter, plus the strip offset
    ex = np.array([v[0] for v in table.column("echo_x").to_pylist()])
    ey = np.array([v[0] for v in table.column("echo_y").to_pylist()])
    ez = np.array([v[0] for v in table.column("echo_z").to_pylist()])
    off = np.array([info["strips"][k]["offset_xyz_m"] for k in kept["strip"]])
    true = kept[["ground_x", "ground_y", "ground_z"]].to_numpy() + off
    err = np.linalg.norm(np.column_stack([ex, ey, ez]) - true, axis=1)
    assert err.max() < sensor.walk_max_m + 5 * sensor.timing_jitter_ns * RANGE_PER_NS
    # anchor + dir * t * RANGE_PER_NS gives every echo (the LAS relation)
    t = np.array([v[0] for v in table.column("echo_time_ns").to_pylist()])
    anchor = np.column_stack([table.column(c).to_numpy() for c in ("anchor_x", "anchor_y", "anchor_z")])
    d = np.column_stack([table.column(c).to_numpy() for c in ("dir_x", "dir_y", "dir_z")])
    assert np.allclose(anchor + d * (t * RANGE_PER_NS)[:, None], np.column_stack([ex, ey, ez]), atol=1e-6)
    assert np.all((t * RANGE_PER_NS >= 3.3) & (t * RANGE_PER_NS <= 4.8))
    # the AGC and the recorded gain law
    agc = table.column("agc").to_numpy()
    assert np.mean(agc) == pytest.approx(info["a"])
    assert np.allclose(truth["gain"], 1 + (truth["agc"] - info["agc"]["law_a"]) * info["agc"]["law_b"])
    assert truth["recorded"].sum() == table.num_rows


def test_xy_error_moves_each_recorded_beam_as_a_whole(tmp_path):
    p, _, still, _, _ = _planar_dataset(tmp_path / "a")
    _, _, moved, _, truth = _planar_dataset(tmp_path / "b", xy_error=0.5)
    rec = truth[truth["recorded"]]
    first = {c: np.array([v[0] for v in t.column(c).to_pylist()]) for t in (still,) for c in ("echo_x", "echo_z")}
    dx = np.array([v[0] for v in moved.column("echo_x").to_pylist()]) - first["echo_x"]
    dz = np.array([v[0] for v in moved.column("echo_z").to_pylist()]) - first["echo_z"]
    assert np.allclose(dz, 0.0)
    assert np.allclose(dx, rec["xy_offset_x"])
    # the recorded sensor moves with the points: the recorded beam is the true one displaced
    for c, o in (("sensor_x", "xy_offset_x"), ("sensor_y", "xy_offset_y")):
        assert np.allclose(moved.column(c).to_numpy() - still.column(c).to_numpy(), rec[o], atol=1e-9)
    assert np.allclose(moved.column("sensor_z").to_numpy(), still.column("sensor_z").to_numpy())
    # a pass over the plane (one strip) lasts well under the correlation time: its pulses share
    # the offset; the strips' offsets are independent draws
    strip = rec["strip"].to_numpy()
    assert len(np.unique(strip)) >= 2
    assert all(dx[strip == k].std() < 0.2 * 0.5 for k in np.unique(strip))  # iid would give 0.5
    assert np.ptp([dx[strip == k].mean() for k in np.unique(strip)]) > 0.0
    assert still.column("samples").equals(moved.column("samples"))


def test_georeferencing_error_is_a_gauss_markov_process():
    """Stationary SD, correlation exp(-lag / tau) and pulses on the trajectory's interpolation."""
    from waveforest.campaign.flight import georeferencing_error

    hz, tau, sd = 10.0, 5.0, 0.25
    t = np.arange(200_000) / hz
    traj = pd.DataFrame({"gps_time": np.concatenate([t, t + 1e5]), "strip": np.repeat([0, 1], t.size)})
    tp = np.array([0.05, 17.33, 1e5 + 3.21])
    off, at_pulses = georeferencing_error(traj, np.array([0, 0, 1]), tp, sd, tau, np.random.default_rng(4))
    a = off[: t.size]
    assert a.std(axis=0) == pytest.approx([sd, sd], rel=0.05)
    lag = int(tau * hz)
    rho = np.mean(a[lag:] * a[:-lag], axis=0) / a.var(axis=0)
    assert rho == pytest.approx([np.exp(-1.0)] * 2, abs=0.03)
    assert abs(np.corrcoef(a[:, 0], a[:, 1])[0, 1]) < 0.02  # axes independent
    assert abs(np.corrcoef(a[:, 0], off[t.size:, 0])[0, 1]) < 0.02  # strips independent
    for i, (k, tt) in enumerate(zip([0, 0, 1], tp)):
        rows = traj["strip"].to_numpy() == k
        assert at_pulses[i, 0] == pytest.approx(np.interp(tt, traj["gps_time"][rows], off[rows, 0]))
