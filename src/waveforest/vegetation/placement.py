"""Horizontal placement of plants in the square plot: uniform or clustered, periodic.

The plot is treated as one tile of an endless canopy: positions (shoot bases, leaf bases)
are wrapped into [-3, 3)^2, so that the leaf area density is the same up to the edges
and the realised LAI is exactly the target (docs/method.md §(g): "shoots at random positions").

Clustering (effect ``clumping``) is a Thomas process (Thomas 1949): cluster centres
(parents) uniform in the plot, each plant assigned to a random parent and displaced from
it by an isotropic Gaussian with standard deviation ``radius`` (m) per axis, then wrapped.
The number of plants is unchanged, so only the spatial pattern changes, not the LAI.
"""

from __future__ import annotations

import numpy as np

from waveforest.vegetation.params import PLOT_HALF_M


def wrap(xy: np.ndarray, half: float = PLOT_HALF_M) -> np.ndarray:
    """Positions wrapped periodically into [-half, half) (any trailing shape (..., k))."""
    side = 2.0 * half
    xy = np.array(xy, dtype=np.float64)
    out = (xy < -half) | (xy >= half)
    if np.any(out):
        v = xy[out]
        xy[out] = v - side * np.floor((v + half) / side)
    return xy


def uniform_positions(n: int, rng: np.random.Generator, half: float = PLOT_HALF_M) -> np.ndarray:
    """``n`` positions uniform in the plot, (n, 2) float64, m."""
    return rng.uniform(-half, half, size=(n, 2))


def thomas_positions(n: int, rng: np.random.Generator, radius: float, per_cluster: float,
                     half: float = PLOT_HALF_M) -> np.ndarray:
    """``n`` positions of a Thomas cluster process, wrapped into the plot.

    Parameters
    ----------
    n : int
        Number of points.
    radius : float, m
        Standard deviation of the Gaussian displacement from the parent, per axis (> 0).
    per_cluster : float
        Mean number of points per cluster (>= 1); n_parents = ceil(n / per_cluster).

    Returns
    -------
    (n, 2) float64, m
    """
    if radius <= 0 or per_cluster < 1:
        raise ValueError(f"thomas_positions: need radius > 0 and per_cluster >= 1, got {radius}, {per_cluster}")
    n_par = max(1, int(np.ceil(n / per_cluster)))
    parents = rng.uniform(-half, half, size=(n_par, 2))
    which = rng.integers(0, n_par, size=n)
    return wrap(parents[which] + rng.normal(0.0, radius, size=(n, 2)), half)


def positions(n: int, rng: np.random.Generator, clumping: float, per_cluster: float,
              half: float = PLOT_HALF_M) -> np.ndarray:
    """Uniform positions for ``clumping == 0``, else a Thomas process of that radius."""
    if clumping > 0:
        return thomas_positions(n, rng, clumping, per_cluster, half)
    return uniform_positions(n, rng, half)
