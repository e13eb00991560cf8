"""Flights: strips, scan pattern, trajectories and the pulses that reach the sites.

Each dataset is flown as parallel strips along the area's long axis, alternating the
azimuths of ``datasets.csv`` (160 deg / 340 deg, docs/method.md §(a)), at a flying height above the
mean terrain H = mean_range / E[sec(theta)] (theta uniform in tan over the swath, so that the
mean range over the swath equals Table 2's mean range). Strips are spaced
2 H tan(theta_max) (1 - overlap) apart across track, at least ``min_strips`` of them,
centred on the area, so every site lies in at least one swath (one or two at 25 % overlap, up
to three at 2012_10_1's 60 %).

Trajectory of a strip (``layout.yaml`` ``flight``): constant ground speed along the planned
line, a slow sinusoidal altitude undulation and lateral sway with random phases; it is
written at ``trajectory_hz`` from the strip's start (a whole second, so the written times are
exact in the CSV's 0.1 ms) and is the exact function the pulses were generated with (linear
interpolation of it is accurate to < 1e-5 m).

Scan pattern: an oscillating mirror (zig-zag) gives scan lines across track spaced
Delta = 1 / sqrt(density) along track, pulses Delta apart along each line (Table 2 waveform
density x ``campaign.density_scale``); each line has its own random across-track phase, and
each pulse's ground point is jittered by ``scan_jitter`` x Delta (mirror and attitude noise).
A line is swept in Delta / v seconds, left to right and back, so a pulse's GPS time is that of
its line plus its position in the sweep; GPS times increase along each strip.

Pulses are generated only where the analysis looks: within a disc around each site
(``radius + disc_margin_m`` for field samples, the same for targets), for every strip whose
swath holds the site ``coverage_margin_m`` inside its 15-deg edge and that records it (a
site's coverage, ``coverage.csv``). A pulse aims at the ground point on the site's ground
plane; its beam is the line from the sensor position at its GPS time to that point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.campaign.layout import Frame
from waveforest.campaign.params import azimuths
from waveforest.rng import stream_generator


def mean_secant(max_zenith_deg: float) -> float:
    """E[sec(theta)] for ground points uniform across a swath of half-angle ``max_zenith_deg``.

    With x = tan(theta) uniform in [-T, T]: (T sqrt(1 + T^2) + asinh T) / (2 T).
    """
    t = np.tan(np.radians(max_zenith_deg))
    return float((t * np.sqrt(1 + t * t) + np.arcsinh(t)) / (2 * t))


@dataclass(frozen=True)
class Strip:
    """One flight line of a dataset (frame coordinates, see :class:`waveforest.campaign.layout.Frame`)."""

    dataset: str
    index: int
    azimuth_deg: float
    direction: int          # +1: flying towards +s, -1: towards -s
    w_line: float           # planned across-track position, m
    t_start: float          # GPS time at s_start, s
    s_start: float
    s_end: float
    speed: float            # m/s
    z_fly: float            # mean flying altitude, m a.s.l.
    und_amp: float
    und_period: float
    und_phase: float
    sway_amp: float
    sway_period: float
    sway_phase: float
    half_swath: float       # nominal half swath width H tan(theta_max), m
    scan_phase: float       # along-track phase of the scan lines, m
    delta: float            # pulse spacing, m

    @property
    def duration(self) -> float:
        """Seconds from s_start to s_end."""
        return abs(self.s_end - self.s_start) / self.speed

    def frame_position(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sensor (s, w, z) at GPS times ``t``."""
        dt = np.asarray(t, dtype=np.float64) - self.t_start
        s = self.s_start + self.direction * self.speed * dt
        w = self.w_line + self.sway_amp * np.sin(2 * np.pi * dt / self.sway_period + self.sway_phase)
        z = self.z_fly + self.und_amp * np.sin(2 * np.pi * dt / self.und_period + self.und_phase)
        return s, w, z


@dataclass(frozen=True)
class FlightPlan:
    """The strips of one dataset and the frame they are expressed in."""

    dataset: str
    frame: Frame
    strips: tuple[Strip, ...]
    max_zenith_deg: float

    def sensor_xyz(self, strip: int, t) -> np.ndarray:
        """(n, 3) world sensor positions of strip ``strip`` at GPS times ``t``, m."""
        s, w, z = self.strips[strip].frame_position(t)
        x, y = self.frame.to_world(s, w)
        return np.stack([x, y, np.broadcast_to(z, np.shape(x))], axis=-1)

    def trajectory(self, hz: float) -> pd.DataFrame:
        """The sensor trajectory of all strips: gps_time, x, y, z, strip (rows in time order)."""
        parts = []
        for st in self.strips:
            n = int(np.ceil(st.duration * hz - 1e-9)) + 1
            t = st.t_start + np.arange(n) / hz
            xyz = self.sensor_xyz(st.index, t)
            parts.append(pd.DataFrame({"gps_time": t, "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
                                       "strip": st.index}))
        return pd.concat(parts, ignore_index=True)


def georeferencing_error(trajectory: pd.DataFrame, pulse_strip: np.ndarray, pulse_time: np.ndarray,
                         sd_m: float, tau_s: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal georeferencing error of the recorded geometry (hidden effect ``xy_error``).

    The drift of a GNSS/INS solution: per strip and axis a stationary Gauss-Markov (AR(1))
    process of SD ``sd_m`` and correlation time ``tau_s``, drawn at the trajectory's times
    and linearly interpolated to the pulses' GPS times. Added to the written trajectory and
    to the recorded points alike, it shifts each recorded beam as a whole, so that the
    recorded beam passes a plant where the real one did not (docs/method.md §(j)), and a trajectory
    read back with linear interpolation gives exactly the pulses' recorded sensor positions.

    Parameters
    ----------
    trajectory : DataFrame
        :meth:`FlightPlan.trajectory` (gps_time, strip; rows in time order within a strip).
    pulse_strip, pulse_time : (n,) int, float64
        Strip index and GPS time of each pulse, s.
    sd_m, tau_s : float
        SD per axis, m; correlation time, s.
    rng : Generator

    Returns
    -------
    trajectory_offset : (m, 2) float64, m
    pulse_offset : (n, 2) float64, m
    """
    t = trajectory["gps_time"].to_numpy(np.float64)
    strip = trajectory["strip"].to_numpy()
    traj_off = np.zeros((len(t), 2))
    pulse_off = np.zeros((len(pulse_time), 2))
    for k in np.unique(strip):  # per strip; its trajectory samples are evenly spaced in time
        rows = np.flatnonzero(strip == k)
        phi = float(np.exp(-(t[rows[1]] - t[rows[0]]) / tau_s)) if len(rows) > 1 else 0.0
        e = rng.standard_normal((len(rows), 2))
        e[1:] *= np.sqrt(1.0 - phi**2)  # x_0 = e_0 ~ N(0, 1) (stationary), x_i = phi x_(i-1) + e_i
        from scipy.signal import lfilter

        traj_off[rows] = sd_m * lfilter([1.0], [1.0, -phi], e, axis=0)
        on = np.flatnonzero(pulse_strip == k)
        for a in range(2):
            pulse_off[on, a] = np.interp(pulse_time[on], t[rows], traj_off[rows, a])
    return traj_off, pulse_off


def plan_flight(row: pd.Series, frame: Frame, layout: dict, density_scale: float, seed: int,
                mean_ground_z: float) -> FlightPlan:
    """The strips of a dataset (module docstring).

    Parameters
    ----------
    row : Series
        A row of :func:`waveforest.campaign.params.load_datasets`.
    frame : Frame
    layout : dict
        ``layout.yaml``.
    density_scale : float
        Scale on the pulse density (config ``campaign.density_scale``).
    seed : int
        Master seed.
    mean_ground_z : float
        Mean terrain elevation under the strips, m.
    """
    if density_scale <= 0:
        raise ValueError("density_scale must be > 0")
    fl, area = layout["flight"], layout["area"]
    rng = stream_generator(seed, "flight", str(row["dataset"]))
    theta = float(row["max_scan_zenith_deg"])
    height = float(row["mean_range_m"]) / mean_secant(theta)
    half = height * np.tan(np.radians(theta))
    spacing = 2 * half * (1 - float(row["strip_overlap"]))
    across = float(area["across_m"])
    n = max(int(row["min_strips"]), int(np.ceil(max(0.0, across - 2 * half) / spacing)) + 1)
    w_lines = (np.arange(n) - (n - 1) / 2) * spacing
    az = azimuths(row)
    speed = float(row["speed_m_s"])
    extent = float(area["along_m"]) / 2 + float(fl["run_in_m"])
    delta = 1.0 / np.sqrt(float(row["pulse_density_m2"]) * density_scale)
    strips = []
    t = float(row["start_gps_time_s"])
    for k in range(n):
        azk = az[k % len(az)]
        direction = 1 if abs(((azk - frame.azimuth_deg) + 180) % 360 - 180) < 90 else -1
        s0, s1 = -direction * extent, direction * extent
        ph = rng.uniform(0, 2 * np.pi, 2)
        strips.append(Strip(
            dataset=str(row["dataset"]), index=k, azimuth_deg=azk, direction=direction, w_line=float(w_lines[k]),
            t_start=t, s_start=s0, s_end=s1, speed=speed, z_fly=mean_ground_z + height,
            und_amp=float(fl["undulation_amp_m"]), und_period=float(fl["undulation_period_s"]), und_phase=float(ph[0]),
            sway_amp=float(fl["sway_amp_m"]), sway_period=float(fl["sway_period_s"]), sway_phase=float(ph[1]),
            half_swath=float(half), scan_phase=float(rng.uniform(0, delta)), delta=float(delta)))
        t = float(np.ceil(t + 2 * extent / speed + float(fl["turn_s"])))  # strips start on whole seconds
    return FlightPlan(str(row["dataset"]), frame, tuple(strips), theta)


PULSE_COLUMNS = ["strip", "site", "gps_time", "sensor_x", "sensor_y", "sensor_z", "ground_x", "ground_y",
                 "ground_z", "dir_x", "dir_y", "dir_z", "range_ground_m", "scan_angle_deg"]
"""Columns of :func:`site_pulses` (true geometry of each pulse)."""


def site_pulses(plan: FlightPlan, sites: pd.DataFrame, layout: dict, seed: int,
                max_per_site: int | None = None) -> pd.DataFrame:
    """The pulses of a dataset that land near its sites, in GPS-time order.

    Parameters
    ----------
    plan : FlightPlan
    sites : DataFrame
        One row per site with columns site (str id), s, w (frame, m), ground_z (m),
        disc_m (radius of the pulse disc, m), optionally coverage (probability that a strip
        whose swath holds the site records it; stream ("coverage", dataset, strip, site)).
    layout : dict
        ``layout.yaml`` (flight.coverage_margin_m, flight.scan_jitter).
    seed : int
        Master seed.
    max_per_site : int or None
        Keep at most this many pulses per site (a random subset; test configs).

    Returns
    -------
    DataFrame
        :data:`PULSE_COLUMNS`; ``dir`` is the unit vector sensor -> ground point,
        ``range_ground_m`` its length, ``scan_angle_deg`` the LAS scan angle (positive to the
        right of the flight direction).
    """
    fl = layout["flight"]
    margin = float(fl["coverage_margin_m"])
    jit = float(fl["scan_jitter"])
    tan_max = np.tan(np.radians(plan.max_zenith_deg))
    ids = sites["site"].astype(str).to_numpy(object)
    s_, w_ = sites["s"].to_numpy(np.float64), sites["w"].to_numpy(np.float64)
    z_, r_ = sites["ground_z"].to_numpy(np.float64), sites["disc_m"].to_numpy(np.float64)
    cov = sites["coverage"].to_numpy(np.float64) if "coverage" in sites else np.ones(len(sites))
    parts = []
    for st in plan.strips:
        covered = np.abs(w_ - st.w_line) <= (st.z_fly - z_) * tan_max - st.sway_amp - margin - r_
        for k in np.flatnonzero(covered):
            if cov[k] < 1 and stream_generator(seed, "coverage", plan.dataset, st.index, ids[k]).random() >= cov[k]:
                continue
            f = _strip_site_pulses(plan, st, ids[k], s_[k], w_[k], z_[k], r_[k], seed, jit)
            if f is not None:
                parts.append(f)
    if not parts:
        return pd.DataFrame({c: [] for c in PULSE_COLUMNS})
    cols = list(zip(*parts))
    df = pd.DataFrame({"strip": np.concatenate(cols[0]), "site": np.concatenate(cols[1]),
                       "gps_time": np.concatenate(cols[2]), "gs": np.concatenate(cols[3]),
                       "gw": np.concatenate(cols[4]), "ground_z": np.concatenate(cols[5])})
    if max_per_site is not None:
        rng = stream_generator(seed, "cap", plan.dataset)
        u = rng.random(len(df))
        rank = pd.Series(u).groupby(df["site"].to_numpy()).rank(method="first").to_numpy()
        df = df[rank <= max_per_site].reset_index(drop=True)
    df = df.sort_values(["strip", "gps_time"], kind="stable").reset_index(drop=True)
    return _pulse_geometry(plan, df)


def _strip_site_pulses(plan: FlightPlan, st, site: str, cs: float, cw: float, gz: float, r: float, seed: int,
                       jit: float) -> tuple | None:
    """The pulses of strip ``st`` within ``r`` (m) of a site at frame (cs, cw), ground ``gz``
    (None if none); the caller has checked that the strip's swath covers the site.

    Scan lines every ``st.delta`` along track, pulses every ``delta`` across with a uniform
    phase per line, both jittered by N(0, jit x delta); the GPS time follows the sweep
    (alternating direction). Stream ("scan", dataset, strip, site). Returns the arrays strip,
    site, gps_time, gs, gw (frame, m), ground_z.
    """
    delta = st.delta
    line_t = delta / st.speed
    rng = stream_generator(seed, "scan", plan.dataset, st.index, site)
    j = np.arange(np.ceil((cs - r - st.scan_phase) / delta), np.floor((cs + r - st.scan_phase) / delta) + 1)
    if j.size == 0:
        return None
    s_line = st.scan_phase + j * delta
    ph = rng.uniform(0, delta, j.size)
    ni = int(np.ceil(2 * r / delta)) + 2
    i = np.arange(ni) - ni // 2
    wn = (cw - st.w_line) - ((cw - st.w_line) % delta) + ph[:, None] + i[None, :] * delta
    sn = np.broadcast_to(s_line[:, None], wn.shape)
    jj = np.broadcast_to(j[:, None], wn.shape)
    sj = sn + rng.normal(0.0, jit * delta, wn.shape)
    wj = st.w_line + wn + rng.normal(0.0, jit * delta, wn.shape)
    keep = np.hypot(sj - cs, wj - cw) <= r
    if not keep.any():
        return None
    sn, wn, jj, sj, wj = sn[keep], wn[keep], jj[keep], sj[keep], wj[keep]
    # time: the sensor passes the scan line at t_line; the sweep crosses the swath in line_t
    t_line = st.t_start + (sn - st.s_start) / (st.direction * st.speed)
    q = np.clip((wn + st.half_swath) / (2 * st.half_swath), 0.0, 1.0)
    q = np.where(jj.astype(np.int64) % 2 == 0, q, 1.0 - q)
    t = t_line + (q - 0.5) * line_t
    n = len(t)
    return (np.full(n, st.index, np.int64), np.full(n, site, object), t, sj, wj, np.full(n, gz))


def _pulse_geometry(plan: FlightPlan, df: pd.DataFrame) -> pd.DataFrame:
    """:data:`PULSE_COLUMNS` of pulses (strip, site, gps_time, gs, gw, ground_z): the sensor
    position on its strip at the GPS time, the unit direction to the ground point, its range, m,
    and the LAS scan angle, degrees (positive to the right of the flight direction)."""
    sensor = np.empty((len(df), 3))
    for st in plan.strips:
        sel = (df["strip"] == st.index).to_numpy()
        if sel.any():
            sensor[sel] = plan.sensor_xyz(st.index, df["gps_time"].to_numpy()[sel])
    gx, gy = plan.frame.to_world(df["gs"], df["gw"])
    ground = np.stack([gx, gy, df["ground_z"].to_numpy(dtype=float)], axis=1)
    d = ground - sensor
    rng_m = np.linalg.norm(d, axis=1)
    unit = d / rng_m[:, None]
    sign = np.array([st.direction for st in plan.strips], dtype=np.float64)[df["strip"].to_numpy(np.int64)]
    heading = sign[:, None] * plan.frame.u[None, :]
    right = np.stack([heading[:, 1], -heading[:, 0]], axis=1)
    across = d[:, 0] * right[:, 0] + d[:, 1] * right[:, 1]
    scan = np.degrees(np.arctan2(across, -d[:, 2]))
    out = pd.DataFrame({
        "strip": df["strip"].to_numpy(np.int64), "site": df["site"].to_numpy(), "gps_time": df["gps_time"].to_numpy(),
        "sensor_x": sensor[:, 0], "sensor_y": sensor[:, 1], "sensor_z": sensor[:, 2],
        "ground_x": ground[:, 0], "ground_y": ground[:, 1], "ground_z": ground[:, 2],
        "dir_x": unit[:, 0], "dir_y": unit[:, 1], "dir_z": unit[:, 2],
        "range_ground_m": rng_m, "scan_angle_deg": scan})
    return out
