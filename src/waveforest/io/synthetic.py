"""Synthetic pulse tables with exact geometry, for writer/reader tests and benchmarks.

Not a sensor model (that is :mod:`waveforest.sensor`): the waveforms are Gaussian echoes on
noise, quantised to the digitizer, which is all the LAS round trip needs. The geometry is
exact: a sensor flying a straight line, a scan across track, and every DR echo on its beam,
``echo = anchor + dir * echo_time_ns * RANGE_PER_NS``.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from ..constants import RANGE_PER_NS
from .tables import PULSE_SCHEMA, padded_to_list

ECHO_FWHM_NS = 4.0
"""FWHM of the synthetic echoes, ns."""
SCAN_ANGLE_STEP_DEG = 0.006
"""Scan angles are multiples of this (the unit of LAS point formats 6-10)."""


def synthetic_pulses(
    n: int,
    seed: int = 0,
    *,
    n_samples: int | tuple[int, ...] = 256,
    sampling_ns: float = 1.0,
    bits: int = 8,
    max_echoes: int = 3,
    altitude_m: float = 800.0,
    max_scan_deg: float = 15.0,
    pulse_rate_hz: float = 100_000.0,
    gps_start: float = 300_000.0,
    origin: tuple[float, float, float] = (500_000.0, 6_800_000.0, 120.0),
    agc: bool = True,
    dataset: str = "synthetic",
    first_pulse_id: int = 0,
) -> pa.Table:
    """A pulse table of ``n`` pulses (:data:`.tables.PULSE_SCHEMA`), deterministic in ``seed``.

    Parameters
    ----------
    n : int
        Pulses.
    seed : int
        Seed of the numpy Generator; same seed -> same table.
    n_samples : int or tuple of int
        Samples per waveform; a tuple draws each pulse's length from it.
    sampling_ns : float
        Sample spacing, ns.
    bits : int
        Digitizer bits: samples are whole numbers in ``[0, 2**bits - 1]``.
    max_echoes : int
        Each pulse has 1..max_echoes DR echoes.
    altitude_m, max_scan_deg, pulse_rate_hz : float
        Flight height above ``origin[2]``, scan half-angle and pulse rate.
    gps_start : float
        GPS time of pulse 0, s (pulse ``i`` is at ``gps_start + (first_pulse_id + i) / pulse_rate_hz``).
    origin : (3,) float
        Start of the flight line on the ground, m.
    agc : bool
        Draw integer AGC values 0..255 (else NaN).
    dataset : str
    first_pulse_id : int
        ``pulse_id`` of the first row (for chunked generation).
    """
    rng = np.random.default_rng(seed)
    ids = first_pulse_id + np.arange(n, dtype=np.int64)
    gps = gps_start + ids / pulse_rate_hz
    # sensor on a straight line along +x at 60 m/s; sawtooth scan across track
    scan_deg = np.round(max_scan_deg * np.sin(2 * np.pi * 70.0 * (gps - gps_start)) / SCAN_ANGLE_STEP_DEG) * SCAN_ANGLE_STEP_DEG
    theta = np.deg2rad(scan_deg)
    sensor = np.stack(
        [origin[0] + 60.0 * (gps - gps_start), np.full(n, origin[1]), np.full(n, origin[2] + altitude_m)], axis=1
    )
    direction = np.stack([np.zeros(n), np.sin(theta), -np.cos(theta)], axis=1)
    ground_z = origin[2] + rng.normal(0.0, 0.3, n)
    ground_range = (sensor[:, 2] - ground_z) / np.cos(theta)

    lengths = np.atleast_1d(np.asarray(n_samples, dtype=np.int64))
    ns = lengths[rng.integers(0, len(lengths), n)] if len(lengths) > 1 else np.full(n, lengths[0])
    record_ns = ns * sampling_ns
    n_echo = rng.integers(1, max_echoes + 1, n)
    # echo times from the first sample: first at 22-32 ns, the others within 30 ns after it (last = ground)
    t_first = rng.uniform(22.0, 32.0, n)
    spread = np.minimum(30.0, 0.6 * record_ns - t_first)
    offsets = np.sort(rng.uniform(0.0, 1.0, (n, max_echoes)), axis=1) * spread[:, None]
    k = np.arange(max_echoes)[None, :]
    offsets[:, 0] = 0.0
    has = k < n_echo[:, None]
    last = np.take_along_axis(offsets, (n_echo - 1)[:, None], axis=1)[:, 0]
    t_echo = np.where(has, t_first[:, None] + offsets, np.nan)
    # the last echo is the ground: this fixes the anchor
    anchor = sensor + direction * (ground_range - (t_first + last) * RANGE_PER_NS)[:, None]
    pos = anchor[:, None, :] + direction[:, None, :] * (t_echo * RANGE_PER_NS)[:, :, None]

    amp = np.where(has, rng.uniform(20.0, 0.8 * (2**bits - 1) - 15.0, (n, max_echoes)), 0.0)
    width = int(lengths.max())
    t = np.arange(width) * sampling_ns
    sigma_ns = ECHO_FWHM_NS / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    wave = np.full((n, width), 10.0)
    for j in range(max_echoes):  # a handful of echo slots, vectorised over pulses and samples
        tj = np.nan_to_num(t_echo[:, j], nan=-1e6)
        wave += amp[:, j, None] * np.exp(-0.5 * ((t[None, :] - tj[:, None]) / sigma_ns) ** 2)
    wave += rng.normal(0.0, 1.5, wave.shape)
    wave = np.clip(np.round(wave), 0, 2**bits - 1).astype(np.float32)

    def lists(values: np.ndarray, type_=None) -> pa.ListArray:
        return padded_to_list(values, n_echo, type_ or pa.float64())

    cols = {
        "dataset": pa.array([dataset]).take(pa.array(np.zeros(n, np.int32))),
        "pulse_id": ids,
        "source": pa.array(["sim"]).take(pa.array(np.zeros(n, np.int32))),
        "gps_time": gps,
        "sensor_x": sensor[:, 0],
        "sensor_y": sensor[:, 1],
        "sensor_z": sensor[:, 2],
        "dir_x": direction[:, 0],
        "dir_y": direction[:, 1],
        "dir_z": direction[:, 2],
        "anchor_x": anchor[:, 0],
        "anchor_y": anchor[:, 1],
        "anchor_z": anchor[:, 2],
        "range_m": np.linalg.norm(pos[:, 0, :] - sensor, axis=1),
        "scan_angle_deg": scan_deg,
        "agc": rng.integers(0, 256, n).astype(np.float64) if agc else np.full(n, np.nan),
        "sampling_ns": np.full(n, float(sampling_ns)),
        "digitizer_gain": np.full(n, 1.0 / (2**bits - 1)),
        "digitizer_offset": np.zeros(n),
        "samples": padded_to_list(wave, ns, pa.float32()),
        "n_echoes": n_echo.astype(np.int16),
        "echo_x": lists(pos[:, :, 0]),
        "echo_y": lists(pos[:, :, 1]),
        "echo_z": lists(pos[:, :, 2]),
        "echo_time_ns": lists(t_echo),
        "echo_intensity": lists(np.round(np.where(has, amp, 0.0)).astype(np.float32), pa.float32()),
    }
    return pa.Table.from_pydict(cols, schema=PULSE_SCHEMA)
