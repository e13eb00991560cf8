"""Trajectory CSV: linear interpolation in time, errors outside it; sensor and range per pulse."""

import numpy as np
import pytest
from fixtures.pulses import synthetic_pulses

from waveforest.io.las.read import read_waveform_las
from waveforest.io.las.write import write_waveform_las
from waveforest.io.trajectory import (
    Trajectory,
    TrajectoryError,
    nominal_range_locator,
    read_trajectory,
    trajectory_locator,
)


def test_linear_motion_is_reproduced_exactly(tmp_path):
    """A sensor in uniform motion: interpolation between 1-s records is exact."""
    t = np.arange(100.0, 111.0)
    v = np.array([55.0, -3.0, 0.5])
    p0 = np.array([500_000.0, 6_800_000.0, 1000.0])
    path = tmp_path / "traj.csv"
    rows = ["gps_time,x,y,z,heading"] + [f"{float(ti)!r},{float(x)!r},{float(y)!r},{float(z)!r},0" for ti, (x, y, z) in zip(t, p0 + (t - 100)[:, None] * v)]
    path.write_text("\n".join(rows[:1] + rows[1:][::-1]))  # any row order
    traj = read_trajectory(path)
    q = np.random.default_rng(0).uniform(100.0, 110.0, 1000)
    np.testing.assert_allclose(traj.position(q), p0 + (q - 100)[:, None] * v, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(traj.position([100.0, 110.0]), [p0, p0 + 10 * v])  # ends included


def test_outside_span_is_an_error():
    traj = Trajectory(np.array([0.0, 1.0]), np.zeros((2, 3)), "t.csv")
    with pytest.raises(TrajectoryError, match=r"t.csv: 2 pulse\(s\) lie outside .*first: gps_time -0.5"):
        traj.position(np.array([0.5, -0.5, 1.5]))


@pytest.mark.parametrize(
    "text, match",
    [
        ("gps_time,x,y\n0,1,2\n1,2,3\n", "lacks column"),
        ("gps_time,x,y,z\n0,1,2,3\n", "at least 2 records"),
        ("gps_time,x,y,z\n0,1,2,3\n0,1,2,3\n", "increase strictly"),
        ("gps_time,x,y,z\n0,1,2,3\n1,a,2,3\n", "column x, data row 2"),
    ],
)
def test_bad_trajectory_files(tmp_path, text, match):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(TrajectoryError, match=match):
        read_trajectory(path)
    with pytest.raises(TrajectoryError, match="no such trajectory"):
        read_trajectory(tmp_path / "missing.csv")


def test_ingested_sensor_and_range_from_trajectory(tmp_path):
    """Synthetic sensor positions as the trajectory: ingest gives them back, and the range."""
    t = synthetic_pulses(200, seed=41)
    path = write_waveform_las(tmp_path / "a.las", t)
    gps = t["gps_time"].to_numpy()
    sensor = np.stack([t[f"sensor_{c}"].to_numpy() for c in "xyz"], axis=1)
    traj = Trajectory(gps, sensor)  # the synthetic sensor flies a straight line: exact
    back = read_waveform_las(path, locate=trajectory_locator(traj))
    got = np.stack([back[f"sensor_{c}"].to_numpy() for c in "xyz"], axis=1)
    np.testing.assert_allclose(got, sensor, rtol=0, atol=1e-6)
    # range = |first echo - sensor|, which also equals the table's own range (to 1 mm quantisation)
    np.testing.assert_allclose(back["range_m"].to_numpy(), t["range_m"].to_numpy(), rtol=0, atol=1e-3)
    # and the sensor lies on the beam behind the anchor
    anchor = np.stack([back[f"anchor_{c}"].to_numpy() for c in "xyz"], axis=1)
    direction = np.stack([back[f"dir_{c}"].to_numpy() for c in "xyz"], axis=1)
    u = anchor - got
    u /= np.linalg.norm(u, axis=1)[:, None]
    np.testing.assert_allclose(u, direction, atol=1e-6)


def test_nominal_range(tmp_path):
    t = synthetic_pulses(50, seed=42)
    path = write_waveform_las(tmp_path / "a.las", t)
    back = read_waveform_las(path, locate=nominal_range_locator(750.0))
    np.testing.assert_array_equal(back["range_m"].to_numpy(), 750.0)
    echo0 = np.stack([np.array([e[0] for e in back[f"echo_{c}"].to_pylist()]) for c in "xyz"], axis=1)
    sensor = np.stack([back[f"sensor_{c}"].to_numpy() for c in "xyz"], axis=1)
    np.testing.assert_allclose(np.linalg.norm(echo0 - sensor, axis=1), 750.0, rtol=1e-12)
    with pytest.raises(TrajectoryError, match="positive"):
        nominal_range_locator(-1.0)
