"""Small synthetic pulse tables with known geometry, for tests of the analysis stages.

Each pulse is a nadir-looking beam from ``altitude`` above its first echo; its waveform is a
sum of Gaussian echoes (``fwhm_ns``) on a constant noise floor, so every quantity a stage
derives (echo positions, heights, times) is known exactly.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from ..constants import RANGE_PER_NS
from ..io.tables import PULSE_SCHEMA, padded_to_list

_SIGMA_PER_FWHM = 1.0 / (2.0 * np.sqrt(2.0 * np.log(2.0)))


def pulse_table(dataset: str, echoes_xyz: list, *, pulse_ids=None, source: str = "real",
                altitude: float = 1000.0, sampling_ns: float = 1.0, n_samples: int = 120,
                pre_m: float = 4.0, amplitude: float = 80.0, fwhm_ns: float = 7.0,
                noise_mean: float = 10.0) -> pa.Table:
    """A pulse table (io.tables.PULSE_SCHEMA) of nadir pulses with the given echoes.

    Parameters
    ----------
    dataset : str
    echoes_xyz : list of (k_i, 3) array-likes, m
        DR echo positions of each pulse (k_i >= 0; all of one pulse on its vertical line).
    pulse_ids : (n,) int, optional
        Default 0..n-1.

    Returns
    -------
    pa.Table
        Sensor ``altitude`` m above the first echo (or above z = 0 without echoes), direction
        (0, 0, -1), the record starting ``pre_m`` before the first echo, Gaussian echoes of
        ``amplitude`` DN above ``noise_mean``.
    """
    n = len(echoes_xyz)
    ids = np.arange(n) if pulse_ids is None else np.asarray(pulse_ids, dtype=np.int64)
    t = np.arange(n_samples) * sampling_ns
    cols: dict = {k: [] for k in ("sensor", "anchor", "range", "n", "ex", "ey", "ez", "et", "ei", "wf")}
    for e in echoes_xyz:
        e = np.asarray(e, dtype=float).reshape(-1, 3)
        top = e[0] if len(e) else np.array([0.0, 0.0, 0.0])
        sensor = top + np.array([0.0, 0.0, altitude])
        anchor = top + np.array([0.0, 0.0, pre_m])
        times = (anchor[2] - e[:, 2]) / RANGE_PER_NS
        wf = np.full(n_samples, noise_mean)
        for tt in times:
            wf += amplitude * np.exp(-0.5 * ((t - tt) / (fwhm_ns * _SIGMA_PER_FWHM)) ** 2)
        cols["sensor"].append(sensor)
        cols["anchor"].append(anchor)
        cols["range"].append(altitude if len(e) else np.nan)
        cols["n"].append(len(e))
        cols["ex"].append(e[:, 0].tolist())
        cols["ey"].append(e[:, 1].tolist())
        cols["ez"].append(e[:, 2].tolist())
        cols["et"].append(times.tolist())
        cols["ei"].append([amplitude] * len(e))
        cols["wf"].append(np.round(wf).astype(np.float32))
    sensor = np.array(cols["sensor"]).reshape(n, 3)
    anchor = np.array(cols["anchor"]).reshape(n, 3)
    wf = np.array(cols["wf"]).reshape(n, n_samples)
    data = {
        "dataset": pa.array([dataset] * n, pa.string()),
        "pulse_id": pa.array(ids, pa.int64()),
        "source": pa.array([source] * n, pa.string()),
        "gps_time": pa.array(ids.astype(float) * 1e-5, pa.float64()),
        "sensor_x": sensor[:, 0], "sensor_y": sensor[:, 1], "sensor_z": sensor[:, 2],
        "dir_x": np.zeros(n), "dir_y": np.zeros(n), "dir_z": -np.ones(n),
        "anchor_x": anchor[:, 0], "anchor_y": anchor[:, 1], "anchor_z": anchor[:, 2],
        "range_m": np.array(cols["range"], dtype=float),
        "scan_angle_deg": np.zeros(n), "agc": np.full(n, np.nan),
        "sampling_ns": np.full(n, sampling_ns), "digitizer_gain": np.ones(n),
        "digitizer_offset": np.zeros(n),
        "samples": padded_to_list(wf, np.full(n, n_samples)),
        "n_echoes": pa.array(np.array(cols["n"], dtype=np.int16), pa.int16()),
        "echo_x": pa.array(cols["ex"], pa.list_(pa.float64())),
        "echo_y": pa.array(cols["ey"], pa.list_(pa.float64())),
        "echo_z": pa.array(cols["ez"], pa.list_(pa.float64())),
        "echo_time_ns": pa.array(cols["et"], pa.list_(pa.float64())),
        "echo_intensity": pa.array(cols["ei"], pa.list_(pa.float32())),
    }
    return pa.table({f.name: pa.array(data[f.name], f.type) if not isinstance(data[f.name], (pa.Array, pa.ChunkedArray))
                     else data[f.name] for f in PULSE_SCHEMA}, schema=PULSE_SCHEMA)


def plate_scene(species: str, height: float, seed: int, *, leaf_rho: float | None = None, leaf_tau: float | None = None,
                ground: bool = True, ground_rho: float = 0.30, **_ignored):
    """A stand-in for ``vegetation.build_scene`` with an analytic answer.

    An opaque horizontal Lambertian plate (kind leaf, rho ``leaf_rho`` (0.47), tau 0) covering
    the 6 x 6 m scene at z = ``height`` above a ground plane (z = 0, ``ground_rho``): a nadir
    pulse sees one echo at H = height with sigma = rho / pi, and nothing else. ``seed``,
    ``species``, ``leaf_tau`` and other keyword arguments are accepted and ignored.
    """
    from ..scene import Scene

    def square(z):
        v = np.array([[-3.0, -3.0, z], [3.0, -3.0, z], [3.0, 3.0, z], [-3.0, 3.0, z]], dtype=np.float32)
        return np.array([[v[0], v[1], v[2]], [v[0], v[2], v[3]]])

    rho = 0.47 if leaf_rho is None else float(leaf_rho)
    tris, rhos, kinds = [square(float(height))], [np.full(2, rho)], [np.full(2, 1)]
    if ground:
        tris.append(square(0.0))
        rhos.append(np.full(2, float(ground_rho)))
        kinds.append(np.full(2, 0))
    return Scene(np.concatenate(tris), np.concatenate(rhos), 0.0, np.concatenate(kinds))
