"""`waveforest survey` against exact answers: flat Lambertian planes, a tilted plane, a step edge.

Every survey is flown end to end (SCENE.yaml + SURVEY.yaml -> LAS + .wdp read back); the
receiver is the als60 preset at 16 bits with a gain and almost no noise, so the recorded
energy is the analytic one up to rounding.

Analytic answers (docs/method.md Eq. 7, sigma a per-bin sum):

- a Lambertian plane of reflectance rho seen at incidence theta gives sigma = rho cos(theta) / pi,
  so the waveform's energy is  G * integral(S) * rho cos(theta) / (pi R^2),  R = H / cos(theta);
- a nadir beam of 1/e diameter d (Gaussian footprint, SD d / (2 sqrt 2) per axis) on a plane
  tilted by alpha spreads sigma(t) with SD  2 (d / (2 sqrt 2)) tan(alpha) / c  (two-way);
- a nadir beam at x0 from a step edge puts the fraction Phi(x0 / sd) of its energy on the upper side.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pyarrow.parquet as pq
import pytest
from fixtures.survey import fly, gaussian_energy, step, tilted_plane, waveform_energy, write_obj
from scipy.special import erf

from waveforest.constants import C_M_PER_NS, RANGE_PER_NS

RECEIVER = {"pulse_rate_hz": 50.0, "scan_frequency_hz": 1.7, "bits": 16, "noise_sd": 0.01}
"""A quiet 16-bit receiver: few pulses over a short leg, rounding far below the signal."""

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def echo_z(table, k: int) -> np.ndarray:
    return np.array([v[k] for v in table.column("echo_z").to_pylist()])


def sigma_moments(truth_file):
    """(n,) total, mean time and SD of each pulse's first-order sigma(t) (truth.parquet)."""
    out = []
    for row in pq.read_table(truth_file).to_pylist():
        s = np.asarray(row["sigma_order_1"])
        t = row["t0_ns"] + (np.arange(len(s)) + 0.5) * row["bin_ns"]
        m = (s * t).sum() / s.sum()
        out.append((s.sum(), m, math.sqrt((s * (t - m) ** 2).sum() / s.sum())))
    return np.array(out)


@pytest.mark.parametrize("theta", [0.0, 20.0])
def test_flat_plane_energy_and_range(tmp_path, theta):
    """Nadir (oscillating mirror at 0 deg) and 20 deg off nadir (conic): energy within 0.5 %,
    every discrete return on the plane within 1 cm along the beam."""
    rho, altitude = 0.3, 1000.0
    scene = {"ground": {"type": "plane", "z": 0.0, "rho": rho, "extent": [-600, -600, 600, 600]}}
    scanner = {**RECEIVER, "pattern": "conic" if theta else "oscillating", "scan_angle_deg": theta, "gain": 100.0}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result, table, sv, _ = fly(tmp_path, scene, scanner, altitude=altitude)
    assert table.num_rows == result["pulses_traced"] >= 3
    cos = math.cos(math.radians(theta))
    expected = gaussian_energy(sv) * rho * cos / math.pi / (altitude / cos) ** 2
    energy = waveform_energy(table, sv.scanner.noise_mean)
    assert np.abs(energy / expected - 1).max() < 0.005
    assert np.all(table.column("n_echoes").to_numpy() == 1)
    assert np.abs(echo_z(table, 0) / cos).max() < 0.01


@pytest.mark.parametrize("tilt", [10.0, 30.0])
def test_tilted_plane_widens_the_echo_as_the_footprint_predicts(tmp_path, tilt):
    """sigma(t) SD = 2 sd tan(alpha) / c within 1 %; the recorded echo's FWHM is that of S(t)
    convolved with it (Gaussians: FWHM^2 add) within 3 %."""
    altitude, divergence = 300.0, 5.0
    write_obj(tmp_path / "plane.obj", tilted_plane(30.0, tilt))
    scene = {"objects": [{"file": "plane.obj", "materials": {"m": {"rho": 0.4}}}], "ground": {"type": "none"}}
    scanner = {**RECEIVER, "scan_angle_deg": 0.0, "divergence_mrad": divergence}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, table, sv, _ = fly(tmp_path, scene, scanner, altitude=altitude, quality={"rays_per_pulse": 4096},
                              output={"truth": True})
    sd_m = altitude * divergence * 1e-3 / (2 * math.sqrt(2))
    sd_t = 2 * sd_m * math.tan(math.radians(tilt)) / C_M_PER_NS
    moments = sigma_moments(tmp_path / "out" / "truth.parquet")
    assert np.abs(moments[:, 2] / sd_t - 1).max() < 0.01
    fwhm_s = sv.scanner.pulse_fwhm_ns
    expected = math.sqrt(fwhm_s**2 + (2 * math.sqrt(2 * math.log(2)) * sd_t) ** 2)
    for samples, dt in zip(table.column("samples").to_pylist(), table.column("sampling_ns").to_numpy()):
        v = np.asarray(samples, float) - sv.scanner.noise_mean
        t = np.arange(len(v)) * dt
        fine = np.arange(0, t[-1], 0.01)
        w = np.interp(fine, t, v)
        above = fine[w >= w.max() / 2]
        assert abs((above[-1] - above[0]) / expected - 1) < 0.03


@pytest.mark.parametrize("x0", [0.3, -0.2])
def test_step_edge_two_echoes_and_energy_split(tmp_path, x0):
    """A 3-m step: two discrete returns, on the plateau and on the ground (within 1 cm), and
    the plateau's share of sigma Phi(x0 / sd) within 1 %."""
    altitude, divergence, h = 300.0, 5.0, 3.0
    write_obj(tmp_path / "step.obj", step(30.0, 0.0, h))
    scene = {"objects": [{"file": "step.obj", "materials": {"m": {"rho": 0.4}}}], "ground": {"type": "none"}}
    scanner = {**RECEIVER, "scan_angle_deg": 0.0, "divergence_mrad": divergence}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, table, _, _ = fly(tmp_path, scene, scanner, x=x0, altitude=altitude, quality={"rays_per_pulse": 4096},
                             output={"truth": True})
    assert np.all(table.column("n_echoes").to_numpy() == 2)
    assert np.abs(echo_z(table, 0) - h).max() < 0.01
    assert np.abs(echo_z(table, 1)).max() < 0.01
    sd_m = altitude * divergence * 1e-3 / (2 * math.sqrt(2))
    expected = 0.5 * (1 + erf(x0 / (sd_m * math.sqrt(2))))
    for row in pq.read_table(tmp_path / "out" / "truth.parquet").to_pylist():
        s = np.asarray(row["sigma_order_1"])
        t = row["t0_ns"] + (np.arange(len(s)) + 0.5) * row["bin_ns"]
        top = s[t * RANGE_PER_NS < altitude - h / 2].sum() / s.sum()
        assert abs(top / expected - 1) < 0.01


def test_each_echo_falls_off_with_its_own_range(tmp_path):
    """Relief under a survey: a plateau 100 m above the scene's lowest level (at 300 m flying
    height) returns G * integral(S) * rho / (pi R^2) at its own range R = 200 m, within 0.5 %
    (R to the lowest level would make it 56 % too faint), and its return lies on it."""
    altitude, h, rho = 300.0, 100.0, 0.4
    write_obj(tmp_path / "step.obj", step(30.0, -10.0, h))
    scene = {"objects": [{"file": "step.obj", "materials": {"m": {"rho": rho}}}], "ground": {"type": "none"}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, table, sv, _ = fly(tmp_path, scene, {**RECEIVER, "scan_angle_deg": 0.0, "gain": 0.1},
                              altitude=altitude)
    expected = gaussian_energy(sv) * rho / math.pi / (altitude - h) ** 2
    assert table.num_rows >= 3
    assert np.abs(waveform_energy(table, sv.scanner.noise_mean) / expected - 1).max() < 0.005
    assert np.abs(echo_z(table, 0) - h).max() < 0.01


def test_a_slope_at_map_grid_coordinates_lies_where_it_does_at_the_origin(tmp_path):
    """A 20-degree slope flown at the origin and again moved to map-grid coordinates (x 6.7e6 m,
    where float32 steps are 0.5 m, and a fraction of a metre off that grid): the returns' heights
    above the slope agree within 2 mm (same pulses, same rays)."""
    import laspy

    write_obj(tmp_path / "slope.obj", tilted_plane(30.0, 20.0))
    offset = {}
    for name, at in (("origin", (0.0, 0.0)), ("utm", (6700000.3, 500000.3))):
        scene = {"objects": [{"file": "slope.obj", "materials": {"m": {"rho": 0.4}},
                              "translate": [*at, 100.0]}], "ground": {"type": "none"}}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fly(tmp_path, scene, {**RECEIVER, "scan_angle_deg": 0.0, "gain": 0.1}, centre=at, out=name)
        las = laspy.read(tmp_path / name / "survey.las")
        x, z = np.asarray(las.x) - at[0], np.asarray(las.z) - 100.0
        offset[name] = (z - x * math.tan(math.radians(20.0))) * math.cos(math.radians(20.0))
    assert len(offset["utm"]) == len(offset["origin"]) >= 3
    assert np.abs(offset["utm"] - offset["origin"]).max() < 0.002


def test_a_ground_plane_far_beyond_the_flight_costs_nothing(tmp_path):
    """The sigma window (truth bins) and start plane follow the tile's beams, not the extent of
    a ground plane: a 6-km plane gives the same window and first-order sigma as a 60-m one."""
    bins = {}
    for half in (30.0, 3000.0):
        scene = {"ground": {"type": "plane", "z": 0.0, "rho": 0.3, "extent": [-half, -half, half, half]}}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fly(tmp_path, scene, {**RECEIVER, "scan_angle_deg": 15.0, "gain": 0.01}, altitude=100.0,
                quality={"rays_per_pulse": 64, "max_order": 3}, output={"truth": True}, out=f"out_{half:g}")
        rows = pq.read_table(tmp_path / f"out_{half:g}" / "truth.parquet").to_pylist()
        bins[half] = [(len(r["sigma_order_1"]), r["t0_ns"], sum(r["sigma_order_1"])) for r in rows]
    assert len(bins[30.0]) >= 3 and bins[30.0] == bins[3000.0]


def test_late_multiple_scattering_is_counted_in_the_summary(tmp_path):
    """A translucent plate 5 m above the ground: light bounced plate -> ground -> plate ... arrives
    after the window's 40 ns for some paths; summary.json says what share of sigma that is."""
    plate = [[(-20, -20, 5), (20, -20, 5), (20, 20, 5), (-20, 20, 5)]]
    write_obj(tmp_path / "plate.obj", plate)
    scene = {"objects": [{"file": "plate.obj", "materials": {"m": {"rho": 0.5, "tau": 0.4, "kind": "leaf"}}}],
             "ground": {"type": "plane", "z": 0.0, "rho": 0.3}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result, _, _, _ = fly(tmp_path, scene, {**RECEIVER, "scan_angle_deg": 0.0, "gain": 0.1}, altitude=300.0,
                              quality={"rays_per_pulse": 4096, "max_order": 7})
    assert 0 < result["sigma_after_window"] < 0.01


def test_truth_joins_the_las_points_by_gps_time(tmp_path):
    """truth.parquet: one row per traced pulse, its GPS time that of the pulse's points, its
    sigma totals rho cos(theta) / pi on a plane."""
    import laspy

    scene = {"ground": {"type": "plane", "z": 0.0, "rho": 0.3, "extent": [-600, -600, 600, 600]}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result, _, _, _ = fly(tmp_path, scene, {**RECEIVER, "scan_angle_deg": 0.0}, output={"truth": True})
    truth = pq.read_table(tmp_path / "out" / "truth.parquet").to_pylist()
    las = laspy.read(tmp_path / "out" / "survey.las")
    assert len(truth) == result["pulses_traced"]
    assert np.allclose(np.sort([r["gps_time"] for r in truth]), np.unique(las.gps_time))
    assert np.allclose([sum(r["sigma_order_1"]) for r in truth], 0.3 / math.pi)
