"""Brute-force Moller-Trumbore intersector in float64: the obviously correct reference."""

from __future__ import annotations

import numpy as np

from waveforest.mcrt.backends.base import RayQueries, check_triangles

NUMPY_BLOCK = 2_000_000
"""Largest rays x triangles block of the NumPy intersector (bounds its memory)."""

MT_DET_EPS = 1e-12
"""Moller-Trumbore: |determinant| below this is a ray parallel to the triangle plane."""


class NumpyIntersector(RayQueries):
    """Every ray against every triangle, in float64.

    Slow (O(rays x triangles)) but obviously correct; the geometric tests run against it and
    against the Embree backends. Both faces of a triangle are hit, ``t > 0``; ``threads`` is
    ignored.
    """

    backend = "numpy"
    tmax_dtype = np.float64

    def __init__(self, triangles: np.ndarray) -> None:
        tri = check_triangles(triangles, np.float64)
        self.v0 = tri[:, 0]
        self.e1 = tri[:, 1] - tri[:, 0]
        self.e2 = tri[:, 2] - tri[:, 0]
        self.n_triangles = len(tri)

    def _all_t(self, o: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(m, n) hit distances, inf where the ray misses the triangle."""
        p = np.cross(d[:, None, :], self.e2[None])
        det = np.einsum("nk,mnk->mn", self.e1, p)
        ok = np.abs(det) > MT_DET_EPS
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o[:, None, :] - self.v0[None]
        u = np.einsum("mnk,mnk->mn", s, p) * inv
        q = np.cross(s, self.e1[None])
        v = np.einsum("mk,mnk->mn", d, q) * inv
        t = np.einsum("nk,mnk->mn", self.e2, q) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        return np.where(hit, t, np.inf)

    def _blocks(self, o: np.ndarray, d: np.ndarray):
        """(a, b, t) per block of rays: t the (b - a, n) hit distances of rays a..b."""
        o, d = o.astype(np.float64), d.astype(np.float64)
        step = max(1, NUMPY_BLOCK // self.n_triangles)
        for a in range(0, len(o), step):
            b = min(len(o), a + step)
            yield a, b, self._all_t(o[a:b], d[a:b])

    def _intersect(self, o, d, tfar, prim, threads, coherent):
        for a, b, t in self._blocks(o, d):
            j = np.argmin(t, axis=1)
            tj = t[np.arange(b - a), j]
            hit = np.isfinite(tj)
            tfar[a:b] = np.where(hit, tj, np.inf)
            prim[a:b] = np.where(hit, j, -1)

    def _occluded(self, o, d, tmax, out, threads):
        for a, b, t in self._blocks(o, d):
            out[a:b] = np.any(t <= tmax[a:b, None], axis=1)
