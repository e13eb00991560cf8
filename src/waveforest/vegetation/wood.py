"""Woody parts (stems, branches, canes) as thin triangular prisms.

A cylinder of diameter d is replaced by a prism whose equilateral cross-section has the same
perimeter, pi d (circumradius R = pi d / (3 sqrt 3)). By Cauchy's formula the mean caliper
width of a convex section is its perimeter / pi, so the prism has the cylinder's mean
projected width and its lateral area (pi d L): the same mean shadow and scattering area.
Each segment is 3 side quads = 6 triangles; the ends are open (they are ~mm^2).
"""

from __future__ import annotations

import math

import numpy as np

PRISM_CIRCUMRADIUS_PER_DIAMETER = math.pi / (3.0 * math.sqrt(3.0))
"""R / d of the equal-perimeter triangular prism."""

_VERTICAL_EPS = 1e-9


def prisms(p0, p1, d0, d1, roll=None) -> np.ndarray:
    """Triangular prisms (frusta) along segments.

    Parameters
    ----------
    p0, p1 : (n, 3) float64, m
        Segment start and end points.
    d0, d1 : (n,) float64, m
        Equivalent cylinder diameters at the start and end.
    roll : (n,) float64, rad, optional
        Rotation of the cross-section about the axis (default 0).

    Returns
    -------
    (6 n, 3, 3) float32, m
        Side triangles with outward right-hand normals, segment by segment.
    """
    p0 = np.asarray(p0, dtype=np.float64)
    p1 = np.asarray(p1, dtype=np.float64)
    n = p0.shape[0]
    if p0.ndim != 2 or p0.shape != p1.shape or p0.shape[1] != 3:
        raise ValueError(f"prisms: p0 and p1 must both be (n, 3), got {p0.shape} and {p1.shape}")
    d0 = np.broadcast_to(np.asarray(d0, dtype=np.float64), (n,))
    d1 = np.broadcast_to(np.asarray(d1, dtype=np.float64), (n,))
    if np.any(d0 < 0) or np.any(d1 < 0):
        raise ValueError("prisms: diameters must be >= 0")
    if n == 0:
        return np.empty((0, 3, 3), dtype=np.float32)
    axis = p1 - p0
    length = np.linalg.norm(axis, axis=1)
    if np.any(length <= 0):
        raise ValueError("prisms: zero-length segment")
    a = axis / length[:, None]
    ref = np.where(np.abs(a[:, 2:3]) < 1 - _VERTICAL_EPS, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(a, ref)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(a, e1)
    ang = (0.0 if roll is None else np.asarray(roll, dtype=np.float64)[:, None]) + \
        np.arange(3)[None, :] * (2.0 * math.pi / 3.0)  # (n, 3)
    ring = np.cos(ang)[..., None] * e1[:, None, :] + np.sin(ang)[..., None] * e2[:, None, :]
    r0 = (PRISM_CIRCUMRADIUS_PER_DIAMETER * d0)[:, None, None]
    r1 = (PRISM_CIRCUMRADIUS_PER_DIAMETER * d1)[:, None, None]
    lo = p0[:, None, :] + r0 * ring  # (n, 3, 3): 3 section corners at the start
    hi = p1[:, None, :] + r1 * ring
    lo_n, hi_n = np.roll(lo, -1, axis=1), np.roll(hi, -1, axis=1)
    # quad k: lo_k, lo_k+1, hi_k+1, hi_k (counter-clockwise seen from outside)
    t1 = np.stack([lo, lo_n, hi_n], axis=2)  # (n, 3, 3, 3)
    t2 = np.stack([lo, hi_n, hi], axis=2)
    return np.concatenate([t1, t2], axis=1).reshape(-1, 3, 3).astype(np.float32)


def polyline_prisms(points, diameters) -> np.ndarray:
    """Prisms along polylines of equal vertex count.

    Parameters
    ----------
    points : (n, k + 1, 3) float64, m
        Vertices of n polylines with k segments each.
    diameters : (n, k + 1) float64, m
        Diameters at the vertices.

    Returns
    -------
    (6 n k, 3, 3) float32
    """
    pts = np.asarray(points, dtype=np.float64)
    d = np.asarray(diameters, dtype=np.float64)
    if pts.ndim != 3 or pts.shape[2] != 3 or d.shape != pts.shape[:2]:
        raise ValueError("polyline_prisms: points (n, k+1, 3) and diameters (n, k+1) expected")
    return prisms(pts[:, :-1].reshape(-1, 3), pts[:, 1:].reshape(-1, 3),
                  d[:, :-1].reshape(-1), d[:, 1:].reshape(-1))
