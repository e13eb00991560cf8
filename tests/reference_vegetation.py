"""Slow, obviously correct NumPy references for the Numba kernels of waveforest.vegetation."""

from __future__ import annotations

import math

import numpy as np


def invert_dewit_bisection(u: np.ndarray, sign: float, freq: float, iters: int = 80) -> np.ndarray:
    """Inverse of F(theta) = (2/pi)(theta + sign sin(freq theta)/freq) by plain bisection.

    F is non-decreasing on [0, pi/2] for the four de Wit types, so bisection on the whole
    interval converges to the (leftmost) root; 80 halvings reach below 1e-16 rad.
    """
    u = np.asarray(u, dtype=np.float64)
    lo = np.zeros_like(u)
    hi = np.full_like(u, 0.5 * math.pi)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        f = 2.0 / math.pi * (mid + sign * np.sin(freq * mid) / freq)
        below = f < u
        lo = np.where(below, mid, lo)
        hi = np.where(below, hi, mid)
    return 0.5 * (lo + hi)


def leaf_frames_reference(normal, toward, eps: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Midrib m (toward projected on the leaf plane, any in-plane axis where it is parallel
    to the normal, normalised) and cross direction b = normal x m, array by array."""
    n, t = np.asarray(normal, dtype=np.float64), np.asarray(toward, dtype=np.float64)
    m = t - np.sum(t * n, axis=1, keepdims=True) * n
    norm = np.linalg.norm(m, axis=1)
    bad = norm < eps * np.maximum(np.linalg.norm(t, axis=1), 1.0)
    alt = np.where(np.abs(n[bad, 0:1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    m[bad] = alt - np.sum(alt * n[bad], axis=1, keepdims=True) * n[bad]
    norm[bad] = np.linalg.norm(m[bad], axis=1)
    m /= norm[:, None]
    return m, np.cross(n, m)


def place_leaves_reference(tri2d: np.ndarray, base, m, b, length, wf) -> np.ndarray:
    """vertex = base + length (x m + wf y b) by broadcasting; (n T, 3, 3) float32."""
    base, m, b = (np.asarray(a, dtype=np.float64) for a in (base, m, b))
    length = np.asarray(length, dtype=np.float64)[:, None, None, None]
    wf = np.asarray(wf, dtype=np.float64)[:, None, None, None]
    x = tri2d[None, :, :, 0:1]
    y = tri2d[None, :, :, 1:2]
    v = base[:, None, None, :] + length * (x * m[:, None, None, :] + wf * y * b[:, None, None, :])
    return v.reshape(-1, 3, 3).astype(np.float32)


def coverage_reference(tri_xy: np.ndarray, x0: float, y0: float, cell: float, nx: int, ny: int) -> np.ndarray:
    """Grid points inside any triangle, testing every point against every triangle.

    A point is inside (or on the edge of) triangle abc when its three barycentric-sign edge
    functions have the sign of the triangle's orientation (or are zero).
    """
    px = x0 + (np.arange(nx) + 0.5) * cell
    py = y0 + (np.arange(ny) + 0.5) * cell
    X, Y = np.meshgrid(px, py)
    out = np.zeros((ny, nx), dtype=bool)
    for (ax, ay), (bx, by), (cx, cy) in np.asarray(tri_xy, dtype=np.float64):
        area2 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area2 == 0:
            continue
        s = np.sign(area2)
        e0 = s * ((bx - ax) * (Y - ay) - (by - ay) * (X - ax))
        e1 = s * ((cx - bx) * (Y - by) - (cy - by) * (X - bx))
        e2 = s * ((ax - cx) * (Y - cy) - (ay - cy) * (X - cx))
        out |= (e0 >= 0) & (e1 >= 0) & (e2 >= 0)
    return out
