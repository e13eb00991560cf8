"""Ray-triangle intersection: an Embree BVH (embreex) and a pure-NumPy brute force behind
one interface, and :func:`prepare`, which turns a :class:`~waveforest.scene.Scene` into the
arrays the tracer needs (METHOD.md d, "First intersection").

Both intersectors take float32 ray origins and directions in the *internal* frame of a
:class:`PreparedScene` (scene coordinates minus ``shift``, the centre of the scene's bounding
box), so that Embree's float32 arithmetic works on numbers of a few metres whatever the
scene's coordinates are. Rays start at ``t = 0`` (Embree's ``tnear``); callers offset new
origins from the surface they leave by :data:`waveforest.constants.RAY_EPS_M`.

The default intersector calls Embree from Numba kernels (:mod:`waveforest.mcrt.rtc`), with a
BVH of HIGH build quality. :class:`EmbreeIntersector` uses embreex's ``run`` instead, which runs
its per-ray loop with the GIL released, so a call is split over ``threads`` Python threads.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..scene import Scene, SceneError

MIN_SPLIT_RAYS = 4096
"""Embree calls with fewer rays than this are not split over threads (thread overhead)."""

NUMPY_BLOCK = 2_000_000
"""Largest rays x triangles block of the NumPy intersector (bounds its memory)."""

MT_DET_EPS = 1e-12
"""Moller-Trumbore: |determinant| below this is a ray parallel to the triangle plane."""

_EMBREE_MISS_T = 1e37
"""tfar that embreex reports for a ray that hit nothing (its default ray length)."""

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


def _default_threads() -> int:
    import numba

    return max(1, int(numba.get_num_threads()))


def _check_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    o = np.ascontiguousarray(origins, dtype=np.float32)
    d = np.ascontiguousarray(directions, dtype=np.float32)
    if o.ndim != 2 or o.shape[1] != 3 or d.shape != o.shape:
        raise ValueError(f"origins, directions: expected two (m, 3) arrays, got {o.shape} and {d.shape}")
    return o, d


class EmbreeIntersector:
    """Nearest-hit and occlusion queries on an Embree 4 BVH through embreex's ``run``.

    The fallback of :func:`prepare` when Embree cannot be called directly
    (:mod:`waveforest.mcrt.rtc`), and a cross-check of the direct path in the tests.

    Parameters
    ----------
    triangles : (n, 3, 3) float32, m
        Triangles in the internal frame (a few metres around the origin).
    """

    backend = "embreex"

    def __init__(self, triangles: np.ndarray) -> None:
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        tri = np.ascontiguousarray(triangles, dtype=np.float32)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3) or len(tri) == 0:
            raise ValueError(f"triangles: expected a non-empty (n, 3, 3) array, got {tri.shape}")
        self._scene = rtcs.EmbreeScene()
        self._mesh = TriangleMesh(self._scene, tri)
        self.n_triangles = len(tri)
        # the first query commits the scene (builds the BVH); do it now, once, single-threaded
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), output=1)

    def _split(self, fn, m: int, threads: int | None):
        threads = _default_threads() if threads is None else max(1, int(threads))
        if threads == 1 or m < MIN_SPLIT_RAYS:
            fn(0, m)
            return
        edges = np.linspace(0, m, threads + 1).astype(int)
        futures = [_pool(threads).submit(fn, a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]
        for f in futures:
            f.result()

    def intersect(self, origins, directions, threads: int | None = None):
        """Nearest hit of each ray.

        Parameters
        ----------
        origins, directions : (m, 3) float32
            Ray origins (internal frame, m) and directions (unit, so that t is in metres).
        threads : int, optional
            Python threads sharing the call (default: Numba's thread count).

        Returns
        -------
        tfar : (m,) float32, m
            Distance to the hit; ``inf`` for a miss.
        prim : (m,) int32
            Index of the triangle hit; -1 for a miss.
        """
        o, d = _check_rays(origins, directions)
        m = len(o)
        tfar = np.empty(m, np.float32)
        prim = np.empty(m, np.int32)
        run = self._scene.run

        def work(a: int, b: int) -> None:
            if b > a:
                res = run(o[a:b], d[a:b], output=1)
                tfar[a:b] = res["tfar"]
                prim[a:b] = res["primID"]

        self._split(work, m, threads)
        tfar[prim < 0] = np.inf
        return tfar, prim

    def occluded(self, origins, directions, tmax, threads: int | None = None):
        """Whether anything lies on each ray between ``t = 0`` and ``tmax``.

        Parameters
        ----------
        origins, directions : (m, 3) float32
        tmax : (m,) float32, m
            Length of each visibility ray.

        Returns
        -------
        (m,) bool
        """
        o, d = _check_rays(origins, directions)
        m = len(o)
        tm = np.array(np.broadcast_to(np.asarray(tmax, np.float32), (m,)))  # embreex writes into it
        out = np.empty(m, np.int32)
        run = self._scene.run

        def work(a: int, b: int) -> None:
            if b > a:
                out[a:b] = run(o[a:b], d[a:b], dists=tm[a:b], query="OCCLUDED")

        self._split(work, m, threads)
        return out != -1


class NumpyIntersector:
    """Brute-force Moller-Trumbore intersector in float64: every ray against every triangle.

    Slow (O(rays x triangles)) but obviously correct; the geometric tests run against it
    and against :class:`EmbreeIntersector`. Both faces of a triangle are hit, ``t > 0``.
    """

    backend = "numpy"

    def __init__(self, triangles: np.ndarray) -> None:
        tri = np.asarray(triangles, dtype=np.float64)
        if tri.ndim != 3 or tri.shape[1:] != (3, 3) or len(tri) == 0:
            raise ValueError(f"triangles: expected a non-empty (n, 3, 3) array, got {tri.shape}")
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

    def _blocks(self, m: int):
        step = max(1, NUMPY_BLOCK // self.n_triangles)
        for a in range(0, m, step):
            yield a, min(m, a + step)

    def intersect(self, origins, directions, threads: int | None = None):
        """Same contract as :meth:`EmbreeIntersector.intersect` (``threads`` is ignored)."""
        o, d = _check_rays(origins, directions)
        o, d = o.astype(np.float64), d.astype(np.float64)
        m = len(o)
        tfar = np.full(m, np.inf, np.float32)
        prim = np.full(m, -1, np.int32)
        for a, b in self._blocks(m):
            t = self._all_t(o[a:b], d[a:b])
            j = np.argmin(t, axis=1)
            tj = t[np.arange(b - a), j]
            hit = np.isfinite(tj)
            tfar[a:b] = np.where(hit, tj, np.inf)
            prim[a:b] = np.where(hit, j, -1)
        return tfar, prim

    def occluded(self, origins, directions, tmax, threads: int | None = None):
        """Same contract as :meth:`EmbreeIntersector.occluded` (``threads`` is ignored)."""
        o, d = _check_rays(origins, directions)
        o, d = o.astype(np.float64), d.astype(np.float64)
        m = len(o)
        tm = np.broadcast_to(np.asarray(tmax, np.float64), (m,))
        out = np.zeros(m, bool)
        for a, b in self._blocks(m):
            t = self._all_t(o[a:b], d[a:b])
            out[a:b] = np.any(t <= tm[a:b, None], axis=1)
        return out


def _embree(triangles: np.ndarray, quality: str):
    """The direct Embree intersector, or embreex's ``run`` if libembree4 cannot be called."""
    from . import rtc

    if rtc.available():
        return rtc.DirectEmbreeIntersector(triangles, quality)
    return EmbreeIntersector(triangles)


BACKENDS = {
    "embree": _embree,
    "embreex": lambda triangles, quality: EmbreeIntersector(triangles),
    "numpy": lambda triangles, quality: NumpyIntersector(triangles),
}
"""Intersector factories by name (:func:`prepare`'s ``backend``): ``embree`` calls Embree from
Numba kernels (:mod:`waveforest.mcrt.rtc`; embreex's ``run`` if that is unavailable),
``embreex`` always uses embreex's ``run``, ``numpy`` is the brute-force reference."""


@dataclass(frozen=True, eq=False)
class PreparedScene:
    """A scene ready to trace: its intersector and per-triangle arrays indexed by primID.

    Build it once with :func:`prepare` and trace it many times.

    Attributes
    ----------
    scene : Scene
        The scene (local coordinates).
    intersector : DirectEmbreeIntersector, EmbreeIntersector or NumpyIntersector
        Works in the internal frame ``local - shift``.
    shift : (3,) float64, m
        Centre of the scene's bounding box; internal = local - shift.
    tri_data : (n, 8) float64
        Per-triangle record read by the kernels (one cache line per triangle): unit normal
        (right-hand rule; zero for a degenerate triangle), rho, tau, kind, 0, 0.
    bounds : (2, 3) float64, m
        Bounding box [min, max] in the internal frame.
    """

    scene: Scene
    intersector: object
    shift: np.ndarray
    tri_data: np.ndarray
    bounds: np.ndarray

    def __len__(self) -> int:
        return len(self.scene)

    @property
    def normals(self) -> np.ndarray:
        """(n, 3) float64 unit normals (internal frame = scene frame, only shifted)."""
        return self.tri_data[:, :3]

    @property
    def rho(self) -> np.ndarray:
        return self.tri_data[:, 3]

    @property
    def tau(self) -> np.ndarray:
        return self.tri_data[:, 4]

    @property
    def kind(self) -> np.ndarray:
        """(n,) int64 element kinds."""
        return self.scene.kind.astype(np.int64)

    @property
    def backend(self) -> str:
        return self.intersector.backend


def _box(triangles: np.ndarray) -> np.ndarray:
    """(2, 3) float64 [min, max] of (n, 3, 3) vertices (axis by axis: NumPy reduces a
    contiguous row far faster than a strided column)."""
    v = np.ascontiguousarray(triangles.reshape(-1, 3).T)
    return np.stack([v.min(axis=1), v.max(axis=1)]).astype(np.float64)


@njit(cache=True, nogil=True)
def _triangle_records(tri, shift, rho, tau, kind):
    """Internal-frame float32 triangles ``tri - shift`` and the (n, 8) records of
    :attr:`PreparedScene.tri_data` (unit normal of the internal triangle by the right-hand
    rule, zero if degenerate; rho, tau, kind; 0, 0)."""
    n = tri.shape[0]
    internal = np.empty((n, 3, 3), np.float32)
    rec = np.zeros((n, 8))
    for i in range(n):
        for v in range(3):
            for a in range(3):
                internal[i, v, a] = np.float32(np.float64(tri[i, v, a]) - shift[a])
        ax = np.float64(internal[i, 1, 0]) - np.float64(internal[i, 0, 0])
        ay = np.float64(internal[i, 1, 1]) - np.float64(internal[i, 0, 1])
        az = np.float64(internal[i, 1, 2]) - np.float64(internal[i, 0, 2])
        bx = np.float64(internal[i, 2, 0]) - np.float64(internal[i, 0, 0])
        by = np.float64(internal[i, 2, 1]) - np.float64(internal[i, 0, 1])
        bz = np.float64(internal[i, 2, 2]) - np.float64(internal[i, 0, 2])
        nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
        length = np.sqrt(nx * nx + ny * ny + nz * nz)
        if length > 0.0:
            rec[i, 0], rec[i, 1], rec[i, 2] = nx / length, ny / length, nz / length
        rec[i, 3], rec[i, 4], rec[i, 5] = rho[i], tau[i], kind[i]
    return internal, rec


def prepare(scene: Scene | PreparedScene, backend: str = "embree", quality: str | None = None) -> PreparedScene:
    """Build the intersector (Embree BVH or NumPy) and the per-triangle arrays of ``scene``.

    Parameters
    ----------
    scene : Scene or PreparedScene
        A prepared scene is returned unchanged.
    backend : {"embree", "embreex", "numpy"}
        See :data:`BACKENDS`; ``numpy`` is a slow brute-force intersector for small tests.
    quality : {"low", "medium", "high"}, optional
        Embree BVH build quality of the ``embree`` backend (default
        :data:`waveforest.mcrt.rtc.DEFAULT_QUALITY`).

    Returns
    -------
    PreparedScene
    """
    if isinstance(scene, PreparedScene):
        return scene
    if not isinstance(scene, Scene):
        raise TypeError(f"scene: expected a waveforest.scene.Scene, got {type(scene).__name__}")
    if len(scene) == 0:
        raise SceneError("scene: no triangles")
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    from .rtc import DEFAULT_QUALITY, QUALITIES

    quality = DEFAULT_QUALITY if quality is None else quality
    if quality not in QUALITIES:
        raise ValueError(f"quality: expected one of {', '.join(QUALITIES)}, got {quality!r}")
    bounds = _box(scene.triangles)
    shift = 0.5 * (bounds[0] + bounds[1])
    internal, tri_data = _triangle_records(scene.triangles, shift, scene.rho, scene.tau, scene.kind)
    return PreparedScene(
        scene=scene,
        intersector=BACKENDS[backend](internal, quality),
        shift=shift,
        tri_data=tri_data,
        bounds=_box(internal),
    )
