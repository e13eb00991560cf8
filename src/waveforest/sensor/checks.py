"""Input checks shared by the public wrappers of the sensor kernels (clear ValueErrors)."""

from __future__ import annotations

import numpy as np


def waveforms(samples, lengths=None, name: str = "samples") -> tuple[np.ndarray, np.ndarray]:
    """A C-contiguous, writable float32 (n, n_s) waveform array and its (n,) int64 valid lengths
    (read-only inputs, such as Arrow columns, are copied: Numba compiles them as another type).

    Samples beyond a row's length may be anything (NaN padding of
    :func:`waveforest.io.pulses.list_to_padded`); samples within it must be finite.
    """
    x = np.asarray(samples)
    if x.ndim != 2:
        raise ValueError(f"{name} must be a 2-D (n_pulses, n_samples) array, got shape {x.shape}")
    if not np.issubdtype(x.dtype, np.floating) and not np.issubdtype(x.dtype, np.integer):
        raise ValueError(f"{name} must be numeric, got dtype {x.dtype}")
    x = np.require(x, np.float32, ["C", "W"])
    n, width = x.shape
    if lengths is None:
        lens = np.full(n, width, dtype=np.int64)
    else:
        lens = np.asarray(lengths)
        if lens.shape != (n,):
            raise ValueError(f"lengths must have shape ({n},), got {lens.shape}")
        if not np.issubdtype(lens.dtype, np.integer):
            if not np.all(np.isfinite(lens)) or np.any(lens != np.round(lens)):
                raise ValueError("lengths must be integers")
        lens = np.require(lens, np.int64, ["C", "W"])
        if n and (lens.min() < 0 or lens.max() > width):
            raise ValueError(f"lengths must lie in [0, {width}] (the samples' width)")
    if n and width:
        valid = np.arange(width)[None, :] < lens[:, None]
        if not np.isfinite(x[valid]).all():
            raise ValueError(f"{name} has non-finite values within the rows' lengths")
    return x, lens


def per_pulse(value, n: int, name: str, *, positive: bool = False, nonnegative: bool = False,
              allow_nan: bool = False) -> np.ndarray:
    """A scalar or (n,) value as a contiguous, writable float64 (n,) array, checked."""
    v = np.asarray(value, dtype=np.float64)
    if v.ndim == 0:
        v = np.full(n, float(v))
    elif v.shape != (n,):
        raise ValueError(f"{name} must be a scalar or have shape ({n},), got {v.shape}")
    v = np.require(v, requirements=["C", "W"])
    finite = np.isfinite(v)
    if not allow_nan and not finite.all():
        raise ValueError(f"{name} must be finite")
    vf = v[finite]
    if positive and (vf <= 0).any():
        raise ValueError(f"{name} must be > 0")
    if nonnegative and (vf < 0).any():
        raise ValueError(f"{name} must be >= 0")
    return v


def gain_or_one(gain) -> np.ndarray:
    """AGC gains with 1 where there is none (NaN or <= 0: a pulse without AGC), float64."""
    g = np.asarray(gain, dtype=np.float64)
    return np.where(np.isfinite(g) & (g > 0), g, 1.0)
