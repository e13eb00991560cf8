"""Embree 4 through embreex's ``EmbreeScene.run``: the fallback when Embree cannot be called
directly (:mod:`.embree`), and a cross-check of that path in the tests.

``run`` loops over rays in Cython with the GIL released, so a call is split over Python
threads; the BVH is embreex's (MEDIUM build quality).
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from waveforest.mcrt.backends.base import RayQueries, check_triangles
from waveforest.mcrt.threads import default_threads

MIN_SPLIT_RAYS = 4096
"""Embree calls with fewer rays than this are not split over threads (thread overhead)."""

_POOL: ThreadPoolExecutor | None = None
_POOL_WORKERS = 0
_POOL_LOCK = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    """A process-wide pool of at least ``workers`` threads for splitting Embree calls."""
    global _POOL, _POOL_WORKERS
    with _POOL_LOCK:
        if _POOL is None or _POOL_WORKERS < workers:
            _POOL = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="waveforest-embree")
            _POOL_WORKERS = workers
        return _POOL


class EmbreeIntersector(RayQueries):
    """Nearest-hit and occlusion queries on an Embree 4 BVH of ``triangles`` (:class:`RayQueries`)
    through embreex's ``run``."""

    backend = "embreex"

    def __init__(self, triangles: np.ndarray) -> None:
        tri = check_triangles(triangles)
        self._scene = rtcs.EmbreeScene()
        self._mesh = TriangleMesh(self._scene, tri)
        self.n_triangles = len(tri)
        # the first query commits the scene (builds the BVH); do it now, once, single-threaded
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), output=1)

    def _split(self, fn, m: int, threads: int | None):
        threads = default_threads() if threads is None else max(1, int(threads))
        if threads == 1 or m < MIN_SPLIT_RAYS:
            fn(0, m)
            return
        edges = np.linspace(0, m, threads + 1).astype(int)
        futures = [_pool(threads).submit(fn, a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        for f in futures:
            f.result()

    def _intersect(self, o, d, tfar, prim, threads, coherent):
        run = self._scene.run

        def work(a: int, b: int) -> None:
            if b > a:
                res = run(o[a:b], d[a:b], output=1)
                tfar[a:b] = res["tfar"]
                prim[a:b] = res["primID"]

        self._split(work, len(o), threads)
        tfar[prim < 0] = np.inf

    def _occluded(self, o, d, tmax, out, threads):
        run = self._scene.run

        def work(a: int, b: int) -> None:
            if b > a:
                out[a:b] = run(o[a:b], d[a:b], dists=tmax[a:b], query="OCCLUDED") != -1

        self._split(work, len(o), threads)
