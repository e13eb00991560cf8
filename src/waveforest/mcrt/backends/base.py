"""The one interface of the ray-triangle intersectors, and the checks they share.

Every backend takes float32 ray origins and directions in the *internal* frame of a
:class:`~waveforest.mcrt.prepare.PreparedScene` (scene coordinates minus its ``shift``), so
that float32 arithmetic works on numbers of a few metres. Rays start at ``t = 0``; callers
offset new origins from the surface they leave by :data:`waveforest.constants.RAY_EPS_M`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Intersector(Protocol):
    """Nearest-hit and occlusion queries on a fixed set of triangles."""

    backend: str
    n_triangles: int

    def intersect(self, origins, directions, threads: int | None = None,
                  coherent: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Nearest hit of each ray: ``tfar`` (m,) float32 in m (inf: miss), ``prim`` (m,) int32 (-1: miss)."""

    def occluded(self, origins, directions, tmax, threads: int | None = None) -> np.ndarray:
        """(m,) bool: whether anything lies on each ray between ``t = 0`` and ``tmax`` (m,)."""


def check_triangles(triangles: np.ndarray, dtype=np.float32) -> np.ndarray:
    """``triangles`` as a contiguous non-empty (n, 3, 3) array of ``dtype``; ValueError otherwise."""
    tri = np.ascontiguousarray(triangles, dtype=dtype)
    if tri.ndim != 3 or tri.shape[1:] != (3, 3) or len(tri) == 0:
        raise ValueError(f"triangles: expected a non-empty (n, 3, 3) array, got {tri.shape}")
    return tri


class RayQueries:
    """The scaffold every backend shares: ray checks, output arrays, the empty batch.

    A backend is built on ``triangles``: (n, 3, 3) float32, m, in the internal frame (a few
    metres around the origin). It implements ``_intersect(o, d, tfar, prim, threads, coherent)`` and
    ``_occluded(o, d, tmax, out, threads)``, which fill the arrays they are given for a
    non-empty batch; :attr:`tmax_dtype` is the precision of the occlusion lengths it compares.
    """

    backend = ""
    tmax_dtype = np.float32

    def intersect(self, origins, directions, threads: int | None = None, coherent: bool = False):
        """Nearest hit of each ray.

        Parameters
        ----------
        origins, directions : (m, 3) float32
            Ray origins (internal frame, m) and directions (unit, so that t is in metres).
        threads : int, optional
            Threads of the call (default: Numba's thread count); a backend may ignore it.
        coherent : bool
            The rays already come in coherent runs (a beam's primary rays, all in one
            footprint): a backend that reorders rays for speed may skip it. Same results.

        Returns
        -------
        tfar : (m,) float32, m
            Distance to the hit; ``inf`` for a miss.
        prim : (m,) int32
            Index of the triangle hit; -1 for a miss.
        """
        o, d = _check_rays(origins, directions)
        tfar = np.empty(len(o), np.float32)
        prim = np.empty(len(o), np.int32)
        if len(o):
            self._intersect(o, d, tfar, prim, threads, coherent)
        return tfar, prim

    def occluded(self, origins, directions, tmax, threads: int | None = None):
        """Whether anything lies on each ray between ``t = 0`` and ``tmax``.

        Parameters
        ----------
        origins, directions : (m, 3) float32
        tmax : (m,) or scalar, m
            Length of each visibility ray.
        threads : int, optional

        Returns
        -------
        (m,) bool
        """
        o, d = _check_rays(origins, directions)
        m = len(o)
        tm = np.array(np.broadcast_to(np.asarray(tmax, self.tmax_dtype), (m,)))  # a backend may write into it
        out = np.empty(m, np.bool_)
        if m:
            self._occluded(o, d, tm, out, threads)
        return out


def _check_rays(origins, directions) -> tuple[np.ndarray, np.ndarray]:
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins, directions: expected two (m, 3) arrays, got {o.shape} and {d.shape}")
    return o, d
