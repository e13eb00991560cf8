"""Sensor trajectories: where the scanner was at each GPS time.

A LAS file does not record the sensor position. A trajectory CSV (columns ``gps_time, x,
y, z``: s and m, in the coordinates of the LAS file; any further columns are ignored)
gives it; positions between two records are linearly interpolated in time. Pulses
outside the trajectory's time span are an error, never extrapolated.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.errors import WaveforestError
from waveforest.io.csvfile import read_csv_file

TRAJECTORY_COLUMNS = ("gps_time", "x", "y", "z")


class TrajectoryError(WaveforestError):
    """A trajectory file that cannot be used."""


@dataclass(frozen=True)
class Trajectory:
    """Sensor positions at increasing GPS times.

    Attributes
    ----------
    gps_time : (n,) float64
        s, strictly increasing, n >= 2.
    xyz : (n, 3) float64
        Sensor position, m.
    source : str
        Where it came from (for messages).
    """

    gps_time: np.ndarray
    xyz: np.ndarray
    source: str = "<trajectory>"

    def __post_init__(self) -> None:
        t = np.asarray(self.gps_time, dtype=np.float64)
        xyz = np.asarray(self.xyz, dtype=np.float64)
        if t.ndim != 1 or len(t) < 2:
            raise TrajectoryError(f"{self.source}: a trajectory needs at least 2 records, got {t.size}")
        if xyz.shape != (len(t), 3):
            raise TrajectoryError(f"{self.source}: positions must have shape ({len(t)}, 3), got {xyz.shape}")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(xyz))):
            raise TrajectoryError(f"{self.source}: gps_time, x, y and z must be finite numbers")
        if np.any(np.diff(t) <= 0):
            k = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise TrajectoryError(
                f"{self.source}: gps_time must increase strictly (record {k + 1}: {float(t[k + 1])!r} after {float(t[k])!r})"
            )
        object.__setattr__(self, "gps_time", t)
        object.__setattr__(self, "xyz", xyz)

    @property
    def span(self) -> tuple[float, float]:
        """First and last GPS time, s."""
        return float(self.gps_time[0]), float(self.gps_time[-1])

    def position(self, gps_time: np.ndarray) -> np.ndarray:
        """Sensor position at each time by linear interpolation.

        Parameters
        ----------
        gps_time : (m,) float64, s

        Returns
        -------
        (m, 3) float64, m

        Raises
        ------
        TrajectoryError
            If any time lies outside the trajectory's span.
        """
        t = np.asarray(gps_time, dtype=np.float64)
        t0, t1 = self.span
        outside = ~((t >= t0) & (t <= t1))
        if np.any(outside):
            k = int(np.flatnonzero(outside)[0])
            raise TrajectoryError(
                f"{self.source}: {int(outside.sum())} pulse(s) lie outside the trajectory's time span "
                f"[{t0!r}, {t1!r}] s (first: gps_time {float(t[k])!r})"
            )
        return np.stack([np.interp(t, self.gps_time, self.xyz[:, k]) for k in range(3)], axis=1)


def read_trajectory(path: str | os.PathLike) -> Trajectory:
    """Read a trajectory CSV (``gps_time, x, y, z``); rows may come in any time order."""

    path = Path(path)
    df = read_csv_file(path, TrajectoryError, what="trajectory file")
    missing = [c for c in TRAJECTORY_COLUMNS if c not in df.columns]
    if missing:
        raise TrajectoryError(
            f"{path}: trajectory lacks column(s) {', '.join(missing)} (expected {', '.join(TRAJECTORY_COLUMNS)})"
        )
    values = {}
    for c in TRAJECTORY_COLUMNS:
        v = pd.to_numeric(df[c], errors="coerce").to_numpy(dtype=np.float64)
        if np.any(~np.isfinite(v)):
            k = int(np.flatnonzero(~np.isfinite(v))[0])
            raise TrajectoryError(f"{path}: column {c}, data row {k + 1}: {str(df[c].iloc[k])!r} is not a finite number")
        values[c] = v
    order = np.argsort(values["gps_time"], kind="stable")
    xyz = np.stack([values["x"], values["y"], values["z"]], axis=1)[order]
    return Trajectory(values["gps_time"][order], xyz, str(path))


def trajectory_locator(trajectory: Trajectory):
    """A pulse locator (see :data:`waveforest.io.las.read.Locator`): sensor from the trajectory, range to the first echo."""

    def locate(gps: np.ndarray, first_echo: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sensor = trajectory.position(gps)
        return sensor, np.linalg.norm(first_echo - sensor, axis=1)

    return locate


def nominal_range_locator(range_m: float):
    """A pulse locator that puts the sensor ``range_m`` before the first echo along the beam."""
    if not (np.isfinite(range_m) and range_m > 0):
        raise TrajectoryError(f"nominal range must be a positive number of metres, got {range_m}")

    def locate(gps: np.ndarray, first_echo: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return first_echo - range_m * direction, np.full(len(gps), float(range_m))

    return locate
