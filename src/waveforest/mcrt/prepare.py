"""A scene made ready to trace: its intersector and the per-triangle arrays the kernels read
(docs/method.md, section d, "First intersection").

The intersector works in an internal frame, scene coordinates minus ``shift`` (the centre of
the scene's bounding box), so that Embree's float32 arithmetic works on numbers of a few
metres whatever the scene's coordinates are.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from waveforest.mcrt.backends import BACKENDS, Intersector
from waveforest.mcrt.backends.embree import DEFAULT_QUALITY, QUALITIES
from waveforest.scene import Scene, SceneError


@dataclass(frozen=True, eq=False)
class PreparedScene:
    """A scene ready to trace: its intersector and per-triangle arrays indexed by primID.

    Build it once with :func:`prepare` and trace it many times.

    Attributes
    ----------
    scene : Scene
        The scene (local coordinates).
    intersector : Intersector
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
    intersector: Intersector
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
    """(2, 3) float64 [min, max] of (n, 3, 3) vertices (reduced axis by axis over a
    contiguous (3, 3n) copy)."""
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
        See :data:`waveforest.mcrt.backends.BACKENDS`; ``numpy`` is a slow brute-force intersector for small tests.
    quality : {"low", "medium", "high"}, optional
        Embree BVH build quality of the ``embree`` backend (default
        :data:`waveforest.mcrt.backends.embree.DEFAULT_QUALITY`).

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
