"""Waveforms aligned on their first echo, for overlays of real and simulated pulses (Fig. 7)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from waveforest.io.pulses import list_to_padded


def align_on_echo(samples: np.ndarray, lengths: np.ndarray, sampling_ns: np.ndarray,
                  echo_time_ns: np.ndarray, grid_ns: np.ndarray) -> np.ndarray:
    """Waveforms linearly interpolated on a time grid relative to each pulse's first echo.

    Parameters
    ----------
    samples : (n, m) float, DN
        Waveforms, padded beyond ``lengths``.
    lengths : (n,) int
        Valid samples per waveform.
    sampling_ns : (n,) float, ns
        Sampling interval of each waveform.
    echo_time_ns : (n,) float, ns
        First-echo time from the first sample (NaN: the row is all NaN).
    grid_ns : (g,) float, ns
        Times relative to the echo at which to interpolate.

    Returns
    -------
    (n, g) float64, DN
        NaN where the grid point lies outside the record.
    """
    samples = np.asarray(samples, dtype=np.float64)
    n, m = samples.shape
    lengths = np.asarray(lengths, dtype=np.int64)
    sampling_ns = np.broadcast_to(np.asarray(sampling_ns, dtype=np.float64), (n,))
    echo = np.asarray(echo_time_ns, dtype=np.float64)
    grid = np.asarray(grid_ns, dtype=np.float64)
    pos = (echo[:, None] + grid[None, :]) / sampling_ns[:, None]
    ok = np.isfinite(pos) & (pos >= 0) & (pos <= (lengths[:, None] - 1))
    pos = np.where(ok, pos, 0.0)
    i0 = np.floor(pos).astype(np.int64)
    i1 = np.minimum(i0 + 1, np.maximum(lengths[:, None] - 1, 0))
    w = pos - i0
    if m == 0:
        return np.full((n, len(grid)), np.nan)
    rows = np.arange(n)[:, None]
    out = (1.0 - w) * samples[rows, np.minimum(i0, m - 1)] + w * samples[rows, np.minimum(i1, m - 1)]
    return np.where(ok, out, np.nan)


def aligned_from_table(pulses: pa.Table, grid_ns: np.ndarray) -> np.ndarray:
    """:func:`align_on_echo` applied to a pulse table (first DR/CFD echo ``echo_time_ns[0]``)."""
    samples, lengths = list_to_padded(pulses.column("samples"))
    times, tl = list_to_padded(pulses.column("echo_time_ns"), dtype=np.float64)
    first = np.where(tl > 0, times[:, 0] if times.shape[1] else np.nan, np.nan)
    sampling = pulses.column("sampling_ns").to_numpy(zero_copy_only=False).astype(float)
    return align_on_echo(samples, lengths, sampling, first, grid_ns)
