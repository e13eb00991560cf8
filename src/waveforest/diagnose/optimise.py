"""The 1-D optimiser of a candidate's fit: parabolic vertex and Brent-like refinement steps.

A gap curve G(u) is known at sorted search coordinates u (docs/method.md §(j), the search;
:mod:`.catalogue` maps u in [0, 1] to an effect's value). :func:`refinement_step` picks the
next u to evaluate (one simulation each): the vertex of the parabola through the best point
and its two neighbours, or a golden-section step into the longer side of the best point's
bracket. :func:`parabolic_vertex` gives the fitted minimum, for one curve or for a (B, k)
stack of bootstrap curves at once. Pure NumPy, no simulation.
"""

from __future__ import annotations

import math

import numpy as np

VERTEX_TOL_U = 1e-3
"""A refinement step closer than this (search coordinate) to an evaluated value is not taken."""

GOLDEN = (3.0 - math.sqrt(5.0)) / 2.0
"""Golden-section fraction (0.382) of Brent's method."""

MAX_BRACKET_ASYMMETRY = 3.0
"""A bracket whose long side exceeds this many times its short side gets a golden step
into the long side: parabolic steps there creep along the short side (slow convergence)."""


def parabolic_vertex(u: np.ndarray, g: np.ndarray) -> float | np.ndarray:
    """Minimum of the parabola through the best evaluated point and its two neighbours.

    Parameters
    ----------
    u : (k,) float64, sorted ascending, k >= 3
    g : (k,) or (B, k) float64
        Gap at each u (several curves: one vertex per row).

    Returns
    -------
    float or (B,) float64
        Vertex clipped to the best point's bracket [u[i-1], u[i+1]]; the best point itself
        where the parabola is not convex; NaN for a curve with a non-finite value.
    """
    single = np.ndim(g) == 1
    g = np.atleast_2d(np.asarray(g, dtype=np.float64))
    u = np.asarray(u, dtype=np.float64)
    k = len(u)
    finite = np.all(np.isfinite(g), axis=1)
    gg = np.where(finite[:, None], g, 0.0)
    i = np.argmin(gg, axis=1)
    j = np.clip(i, 1, k - 2)
    x0, x1, x2 = u[j - 1], u[j], u[j + 1]
    rows = np.arange(len(g))
    y0, y1, y2 = gg[rows, j - 1], gg[rows, j], gg[rows, j + 1]
    den = (x0 - x1) * (x0 - x2) * (x1 - x2)
    a = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / den
    b = (x2**2 * (y0 - y1) + x1**2 * (y2 - y0) + x0**2 * (y1 - y2)) / den
    lo, hi = u[np.maximum(i - 1, 0)], u[np.minimum(i + 1, k - 1)]
    with np.errstate(divide="ignore", invalid="ignore"):
        vertex = np.clip(-b / (2 * a), lo, hi)
    out = np.where(a > 0, vertex, u[i])
    out = np.where(finite, out, np.nan)
    return float(out[0]) if single else out


def refinement_step(u: np.ndarray, g: np.ndarray) -> float | None:
    """Next value to evaluate: a Brent-like step inside the bracket of the best point.

    The vertex of the parabola through the best point and its neighbours, unless the
    bracket is lopsided (:data:`MAX_BRACKET_ASYMMETRY`), the parabola is not convex or its
    vertex is within :data:`VERTEX_TOL_U` of an evaluated value; then the golden-section
    point of the longer side of the bracket (which always shrinks the bracket, so strongly
    asymmetric curves, e.g. the tanh saturation, still converge). None when the bracket is
    narrower than the tolerance.

    Parameters
    ----------
    u : (k,) float64, sorted ascending
    g : (k,) float64
    """
    i = int(np.argmin(g))
    lo, hi = u[max(i - 1, 0)], u[min(i + 1, len(u) - 1)]
    if hi - lo < 2 * VERTEX_TOL_U:
        return None
    left, right = u[i] - lo, hi - u[i]
    golden = u[i] + GOLDEN * right if right >= left else u[i] - GOLDEN * left
    lopsided = min(left, right) > 0 and max(left, right) > MAX_BRACKET_ASYMMETRY * min(left, right)
    if not lopsided:
        j = min(max(i, 1), len(u) - 2)
        x0, x1, x2 = u[j - 1], u[j], u[j + 1]
        y0, y1, y2 = g[j - 1], g[j], g[j + 1]
        convex = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / ((x0 - x1) * (x0 - x2) * (x1 - x2)) > 0
        v = parabolic_vertex(u, g)
        if convex and np.min(np.abs(u - v)) >= VERTEX_TOL_U:
            return float(v)
    return None if np.min(np.abs(u - golden)) < VERTEX_TOL_U else float(golden)
