"""The platform and the scanner: GPS time, sensor position and beam direction of every pulse.

Body frame of the platform: ``fwd`` (heading), ``right``, ``up``. A pulse's body direction is,
with ``p`` the phase (scan frequency x time since the start of its leg, fractional part) and
``a`` the largest scan angle:

- ``oscillating`` mirror: angle ``a (1 - 4 |p - 1/2|)`` across track (zig-zag lines, two per cycle);
- ``polygon``: angle ``a (2 p - 1)`` across track (saw-tooth lines, one per facet);
- ``conic`` (Palmer): zenith ``a`` at azimuth ``2 pi p`` from the heading.

Roll turns the body about ``fwd`` (right wing down for positive roll), pitch about ``right``
(nose up for positive pitch), heading is clockwise from +y (north). The LAS scan angle is the
across-track angle of the beam from the vertical, positive to the right.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.io.csvfile import read_csv_file
from waveforest.survey.spec import Scanner, Survey, SurveyError

TRAJECTORY_ATTITUDE = ("gps_time", "x", "y", "z", "roll_deg", "pitch_deg", "heading_deg")


@dataclass(frozen=True)
class Track:
    """Platform states at increasing times of one leg."""

    gps_time: np.ndarray   # (n,) s
    xyz: np.ndarray        # (n, 3) m
    attitude: np.ndarray   # (n, 3) roll, pitch, heading, degrees


@dataclass(frozen=True)
class Pulses:
    """Every pulse of a survey, in time order within each leg."""

    leg: np.ndarray        # (n,) int64
    gps_time: np.ndarray   # (n,) s
    origin: np.ndarray     # (n, 3) m
    direction: np.ndarray  # (n, 3) unit
    scan_angle_deg: np.ndarray
    scan_flags: np.ndarray  # (n,) uint8: SCAN_POSITIVE, EDGE_OF_LINE (LAS 1.4 R15 point flags)

    def __len__(self) -> int:
        return len(self.gps_time)

    def take(self, idx) -> Pulses:
        return Pulses(*(getattr(self, f)[idx] for f in PULSE_FIELDS))


PULSE_FIELDS = ("leg", "gps_time", "origin", "direction", "scan_angle_deg", "scan_flags")

SCAN_POSITIVE, EDGE_OF_LINE = 1, 2
"""Bits of :attr:`Pulses.scan_flags`: the mirror moves left to right across track (LAS scan
direction flag 1), and the pulse is the last of its scan line before the mirror turns or the
facet changes (edge of flight line)."""


def leg_tracks(survey: Survey) -> list[Track]:
    """The legs as tracks (two states each: straight, level, heading along the leg), or the trajectory table."""
    if survey.trajectory is not None:
        df = read_csv_file(survey.trajectory, SurveyError, what="trajectory file")
        missing = [c for c in TRAJECTORY_ATTITUDE if c not in df.columns]
        if missing:
            raise SurveyError(f"{survey.trajectory}: missing column(s) {', '.join(missing)} "
                              f"(expected {', '.join(TRAJECTORY_ATTITUDE)})")
        values = {}
        for c in TRAJECTORY_ATTITUDE:
            v = pd.to_numeric(df[c], errors="coerce").to_numpy(np.float64)
            bad = np.flatnonzero(~np.isfinite(v))
            if bad.size:
                raise SurveyError(f"{survey.trajectory}: column {c}, row {int(bad[0]) + 2}: expected a finite "
                                  f"number, got {str(df[c].iloc[bad[0]])!r}")
            values[c] = v
        t = values["gps_time"]
        if len(t) < 2 or np.any(np.diff(t) <= 0):
            raise SurveyError(f"{survey.trajectory}: gps_time: expected at least 2 strictly increasing times")
        # angles unwrapped, so that 359.9 -> 0.1 deg interpolates through 0, not through 180
        att = np.column_stack([np.unwrap(values[c], period=360.0) for c in TRAJECTORY_ATTITUDE[4:]])
        return [Track(t, np.column_stack([values[c] for c in "xyz"]), att)]
    out, t = [], survey.start_gps_time_s
    for g in survey.legs:
        a, b = np.array([*g.start, g.altitude_m]), np.array([*g.end, g.altitude_m])
        duration = float(np.hypot(*(b - a)[:2])) / g.speed_m_s
        heading = float(np.degrees(np.arctan2(b[0] - a[0], b[1] - a[1])))
        out.append(Track(np.array([t, t + duration]), np.stack([a, b]), np.array([[0.0, 0.0, heading]] * 2)))
        t = t + duration + survey.turn_s
    return out


def body_directions(scanner: Scanner, phase: np.ndarray) -> np.ndarray:
    """(n, 3) unit beam directions in (right, fwd, up) at scan phases ``phase`` in [0, 1)."""
    a = np.radians(scanner.scan_angle_deg)
    if scanner.pattern == "conic":
        az = 2 * np.pi * phase
        return np.stack([np.sin(a) * np.sin(az), np.sin(a) * np.cos(az), -np.full_like(phase, np.cos(a))], axis=1)
    if scanner.pattern == "oscillating":
        ang = a * (1.0 - 4.0 * np.abs(phase - 0.5))
    else:  # polygon
        ang = a * (2.0 * phase - 1.0)
    return np.stack([np.sin(ang), np.zeros_like(ang), -np.cos(ang)], axis=1)


def world_directions(body: np.ndarray, attitude: np.ndarray) -> np.ndarray:
    """Body directions (right, fwd, up) turned by roll, pitch and heading (degrees, (n, 3))."""
    r, p, h = (np.radians(attitude[:, k]) for k in range(3))
    x, y, z = body[:, 0], body[:, 1], body[:, 2]
    x, z = x * np.cos(r) + z * np.sin(r), -x * np.sin(r) + z * np.cos(r)   # roll about fwd
    y, z = y * np.cos(p) - z * np.sin(p), y * np.sin(p) + z * np.cos(p)    # pitch about right (nose up)
    fwd = np.stack([np.sin(h), np.cos(h)], axis=1)
    right = np.stack([np.cos(h), -np.sin(h)], axis=1)
    xy = x[:, None] * right + y[:, None] * fwd
    d = np.column_stack([xy, z])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def fly_blocks(survey: Survey, tracks: list[Track], block: int = 1_000_000):
    """Every pulse of every track in blocks of at most ``block`` pulses, in time order (pulse k
    of a track at ``t0 + k / pulse_rate``), so that a long flight never sits in memory whole.
    A track's pulses at or before the previous track's last pulse (``turn_s`` 0: a leg starting
    when the last ends) are not flown, so no two pulses share a GPS time."""
    sc = survey.scanner
    last = -np.inf
    for i, tr in enumerate(tracks):
        n = int(np.floor((tr.gps_time[-1] - tr.gps_time[0]) * sc.pulse_rate_hz)) + 1
        first = int(np.floor((last - tr.gps_time[0]) * sc.pulse_rate_hz)) + 1 if last >= tr.gps_time[0] else 0
        last = tr.gps_time[0] + (n - 1) / sc.pulse_rate_hz
        for a in range(first, n, block):
            dt = np.arange(a, min(n, a + block)) / sc.pulse_rate_hz
            t = tr.gps_time[0] + dt
            xyz = np.stack([np.interp(t, tr.gps_time, tr.xyz[:, k]) for k in range(3)], axis=1)
            att = np.stack([np.interp(t, tr.gps_time, tr.attitude[:, k]) for k in range(3)], axis=1)
            body = body_directions(sc, np.mod(dt * sc.scan_frequency_hz, 1.0))
            d = world_directions(body, att)
            h = np.radians(att[:, 2])
            across = d[:, 0] * np.cos(h) - d[:, 1] * np.sin(h)
            scan = np.degrees(np.arctan2(across, -d[:, 2]))
            yield Pulses(np.full(len(t), i, np.int64), t, xyz, d, scan, scan_flags(sc, dt))


SLOPE_PHASE = 1e-6
"""Phase step (of a scan period) before a pulse over which the mirror's direction is taken."""


def scan_flags(scanner: Scanner, dt: np.ndarray) -> np.ndarray:
    """(n,) uint8 :data:`SCAN_POSITIVE` | :data:`EDGE_OF_LINE` of pulses ``dt`` s into their leg,
    from the mirror alone (not the platform's attitude), as LAS 1.4 R15 defines them: the
    direction the mirror travels when the pulse leaves (a polygon sweeps left to right on every
    facet), and the last pulse of a sweep before the mirror turns (or the facet changes). An
    oscillating or conic mirror's direction is that of its across-track angle arriving at the
    pulse's phase, so a pulse at the turn ends its sweep."""
    step, f = 1.0 / scanner.pulse_rate_hz, scanner.scan_frequency_hz
    if scanner.pattern == "polygon":
        phase, after = np.mod(dt * f, 1.0), np.mod((dt + step) * f, 1.0)
        return (SCAN_POSITIVE + (after < phase) * EDGE_OF_LINE).astype(np.uint8)

    def rising(t):
        ang = [np.arctan2(b[:, 0], -b[:, 2]) for b in
               (body_directions(scanner, np.mod(u * f, 1.0)) for u in (t - SLOPE_PHASE / f, t))]
        return ang[1] > ang[0]

    now, then = rising(dt), rising(dt + step)
    return (now * SCAN_POSITIVE + (now != then) * EDGE_OF_LINE).astype(np.uint8)


def concat(parts: list[Pulses]) -> Pulses:
    """The pulses of ``parts`` one after the other."""
    return Pulses(*(np.concatenate([getattr(p, f) for p in parts]) for f in PULSE_FIELDS))


def fly(survey: Survey, tracks: list[Track]) -> Pulses:
    """Every pulse of every track (:func:`fly_blocks` in one piece)."""
    return concat(list(fly_blocks(survey, tracks)))


def trajectory_table(tracks: list[Track], hz: float) -> pd.DataFrame:
    """The written trajectory: gps_time, x, y, z, roll_deg, pitch_deg, heading_deg, leg (``hz`` per s;
    leg from 1, the point source ID of its points)."""
    parts = []
    for i, tr in enumerate(tracks):
        n = int(np.ceil((tr.gps_time[-1] - tr.gps_time[0]) * hz - 1e-9)) + 1
        t = np.minimum(tr.gps_time[0] + np.arange(n) / hz, tr.gps_time[-1])
        cols = {"gps_time": t}
        for k, c in enumerate("xyz"):
            cols[c] = np.interp(t, tr.gps_time, tr.xyz[:, k])
        for k, c in enumerate(("roll_deg", "pitch_deg", "heading_deg")):
            a = np.interp(t, tr.gps_time, tr.attitude[:, k])
            a = np.round(a, 6)  # as written (6 decimals), so that a heading just below 360 is written 0
            cols[c] = np.mod(a, 360.0) if c == "heading_deg" else (a + 180.0) % 360.0 - 180.0
        cols["leg"] = i + 1
        parts.append(pd.DataFrame(cols))
    return pd.concat(parts, ignore_index=True)


def axis_hits_box(origin: np.ndarray, direction: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(n,) bool: the beam axis (a ray) passes through the box [min, max] (slab test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        t1, t2 = (box[0] - origin) * inv, (box[1] - origin) * inv
    lo = np.nanmax(np.minimum(t1, t2), axis=1)
    hi = np.nanmin(np.maximum(t1, t2), axis=1)
    return (hi >= np.maximum(lo, 0.0))
