"""Reference targets of a campaign and the pulses that hit them (docs/method.md §(b), e).

``targets.csv`` (the schema the virtual campaign writes and a user fills in):
target_id, year, material, hdrf (nadir HDRF at 1064 nm; empty for AGC-only targets),
calibration (0/1: used for S(t), Eq. 8), agc (0/1: used to fit b of Eq. 1), x, y, z, radius_m.

``datasets.csv``: dataset, year, ... (the sensor stages use the dataset's year).

A pulse belongs to a target if its first DR echo (echo_x[0], echo_y[0]) lies within
radius_m of the target centre (x, y) and the target's year is the dataset's year; if several
targets qualify, the nearest centre wins.

The tables have one reader, :mod:`waveforest.io.tables`, whose checks every stage shares.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa

from waveforest.io.pulses import list_to_padded

__all__ = ["target_membership", "first_echo_xy", "pulse_targets"]


def target_membership(x, y, year: int, targets: pd.DataFrame) -> np.ndarray:
    """Index (row position in ``targets``) of the target each point lies on, -1 for none.

    Parameters
    ----------
    x, y : (n,) float, m (first DR echo positions; NaN = no echo -> -1).
    year : int, the dataset's year (only targets of that year count).
    targets : DataFrame with x, y, radius_m, year.

    Returns
    -------
    (n,) int64
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError("x and y must be 1-D arrays of equal length")
    out = np.full(x.shape, -1, dtype=np.int64)
    cand = np.flatnonzero(targets["year"].to_numpy() == year)
    if cand.size == 0 or x.size == 0:
        return out
    tx = targets["x"].to_numpy(np.float64)[cand]
    ty = targets["y"].to_numpy(np.float64)[cand]
    tr = targets["radius_m"].to_numpy(np.float64)[cand]
    chunk = max(1, 4_000_000 // cand.size)
    for s in range(0, x.size, chunk):  # bounded memory; a handful of chunks, not a loop per pulse
        d2 = (x[s:s + chunk, None] - tx[None, :]) ** 2 + (y[s:s + chunk, None] - ty[None, :]) ** 2
        d2 = np.where(d2 <= tr[None, :] ** 2, d2, np.inf)
        best = np.argmin(d2, axis=1)
        hit = np.isfinite(d2[np.arange(d2.shape[0]), best])
        out[s:s + chunk] = np.where(hit, cand[best], -1)
    return out


def first_echo_xy(pulses: pa.Table) -> tuple[np.ndarray, np.ndarray]:
    """(echo_x[0], echo_y[0]) of every pulse, NaN without echoes."""
    res = []
    for c in ("echo_x", "echo_y"):
        vals, lens = list_to_padded(pulses.column(c), dtype=np.float64)
        v = np.full(pulses.num_rows, np.nan)
        if vals.shape[1]:
            v[lens > 0] = vals[lens > 0, 0]
        res.append(v)
    return res[0], res[1]


def pulse_targets(pulses: pa.Table, targets: pd.DataFrame, year: int) -> np.ndarray:
    """Target index of each pulse of a pulse table (first DR echo within radius), -1 for none."""
    x, y = first_echo_xy(pulses)
    return target_membership(x, y, year, targets)
