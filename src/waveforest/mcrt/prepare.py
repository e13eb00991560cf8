"""A scene made ready to trace: its intersector and the per-triangle arrays the kernels read
(docs/method.md, section d, "First intersection").

The intersector works in an internal frame, scene coordinates minus ``shift`` (the centre of
the scene's bounding box), so that Embree's float32 arithmetic works on numbers of a few
metres whatever the scene's coordinates are.

A scene made of rigid copies of a few parts (e.g. a canopy assembled from a library of
leaf bricks, a new arrangement for every pulse) is prepared in two steps: the parts once
(:func:`prepare_prototypes`, one BVH each), then each arrangement (:func:`prepare_instances`:
a top-level BVH over the copies, and the copies' per-triangle records).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from waveforest.mcrt.backends import BACKENDS, Intersector
from waveforest.mcrt.backends.embree import (
    DEFAULT_QUALITY,
    QUALITIES,
    DirectEmbreeIntersector,
    InstancedEmbreeIntersector,
)
from waveforest.scene import Scene, SceneError


@dataclass(frozen=True, eq=False)
class PreparedScene:
    """A scene ready to trace: its intersector and per-triangle arrays indexed by primID.

    Build it once with :func:`prepare` and trace it many times.

    Attributes
    ----------
    scene : Scene or None
        The scene (local coordinates); None for an arrangement of instances
        (:func:`prepare_instances`), whose triangles are never assembled.
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

    scene: Scene | None
    intersector: Intersector
    shift: np.ndarray
    tri_data: np.ndarray
    bounds: np.ndarray

    def __len__(self) -> int:
        return len(self.tri_data)

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
        return self.tri_data[:, 5].astype(np.int64)

    @property
    def backend(self) -> str:
        return self.intersector.backend


@njit(cache=True, nogil=True)
def _box(tri):  # pragma: no cover - compiled; tested against NumPy
    """(2, 3) float64 [min, max] of the (n, 3, 3) vertices ``tri`` (finite), in one pass."""
    box = np.empty((2, 3))
    box[0, :], box[1, :] = np.inf, -np.inf
    for i in range(tri.shape[0]):
        for v in range(3):
            for a in range(3):
                x = np.float64(tri[i, v, a])
                box[0, a] = min(box[0, a], x)
                box[1, a] = max(box[1, a], x)
    return box


@njit(cache=True, nogil=True)
def _triangle_records(tri, shift, rho, tau, kind):
    """Internal-frame float32 triangles ``tri - shift``, the (n, 8) records of
    :attr:`PreparedScene.tri_data` (unit normal of the internal triangle by the right-hand
    rule, zero if degenerate; rho, tau, kind; 0, 0) and the internal triangles' (2, 3) box."""
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
    return internal, rec, _box(internal)


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
    internal, tri_data, box = _triangle_records(scene.triangles, shift, scene.rho, scene.tau, scene.kind)
    return PreparedScene(
        scene=scene,
        intersector=BACKENDS[backend](internal, quality),
        shift=shift,
        tri_data=tri_data,
        bounds=box,
    )


def with_optics(prepared: PreparedScene, scene: Scene) -> PreparedScene:
    """``scene`` prepared on the BVH of ``prepared``, whose triangles it must have (checked):
    only its rho, tau and kind differ, so it costs the per-triangle records, not a BVH build.

    Raises ValueError when ``prepared`` holds no scene (instances) or other triangles."""
    own = prepared.scene
    if own is None or own.triangles.shape != scene.triangles.shape or not np.array_equal(own.triangles,
                                                                                         scene.triangles):
        raise ValueError("scene: expected the triangles of the prepared scene (only the optics may differ)")
    tri_data = prepared.tri_data.copy()
    tri_data[:, 3], tri_data[:, 4], tri_data[:, 5] = scene.rho, scene.tau, scene.kind
    return PreparedScene(scene=scene, intersector=prepared.intersector, shift=prepared.shift, tri_data=tri_data,
                         bounds=prepared.bounds)


@dataclass(frozen=True, eq=False)
class Prototypes:
    """Parts prepared once, to be copied into many arrangements (:func:`prepare_instances`).

    Attributes
    ----------
    scenes : tuple of PreparedScene
        Each part with its own BVH (``embree`` backend) in its own internal frame.
    records : (N, 8) float64
        The parts' ``tri_data`` one after the other.
    starts : (P + 1,) int64
        Part ``p`` has records ``starts[p]:starts[p + 1]``.
    """

    scenes: tuple
    records: np.ndarray
    starts: np.ndarray

    def __len__(self) -> int:
        return len(self.scenes)


def prepare_prototypes(scenes: Sequence[Scene], quality: str = "high") -> Prototypes:
    """Prepare the parts of :func:`prepare_instances` (``embree`` backend; HIGH quality by
    default: a part's BVH is built once and traced in every arrangement)."""
    prepared = tuple(prepare(s, "embree", quality) for s in scenes)
    if not prepared:
        raise ValueError("scenes: expected at least one prototype")
    starts = np.cumsum([0] + [len(p) for p in prepared]).astype(np.int64)
    return Prototypes(prepared, np.concatenate([p.tri_data for p in prepared]), starts)


@njit(cache=True, nogil=True)
def _instance_records(records, starts, which, rotation, offsets, out):
    """``out[offsets[j] + i]`` = record ``i`` of prototype ``which[j]`` with its normal
    turned by ``rotation[j]`` (the rest copied)."""
    for j in range(which.shape[0]):
        a, b = starts[which[j]], starts[which[j] + 1]
        o = offsets[j]
        for i in range(b - a):
            r = records[a + i]
            for c in range(3):
                out[o + i, c] = rotation[j, c, 0] * r[0] + rotation[j, c, 1] * r[1] + rotation[j, c, 2] * r[2]
            for c in range(3, 8):
                out[o + i, c] = r[c]


def prepare_instances(prototypes: Prototypes, which, rotation, translation, quality: str = "medium") -> PreparedScene:
    """A scene of rigid copies of prepared parts: a two-level Embree BVH (only the top level,
    one box per copy, is built here) and the copies' per-triangle records.

    Parameters
    ----------
    prototypes : Prototypes
        From :func:`prepare_prototypes`.
    which : (k,) int
        Part of each copy.
    rotation : (k, 3, 3) float
        Rotation of each copy (orthonormal, determinant +1).
    translation : (k, 3) float, m
        A point x of part ``which[j]`` (its local coordinates) lies at
        ``rotation[j] @ x + translation[j]`` in the scene.
    quality : {"low", "medium", "high"}
        Build quality of the top level.

    Returns
    -------
    PreparedScene
        ``scene`` None; triangle ``offsets[j] + i`` is triangle ``i`` of copy ``j`` (copies
        in order); traced by :func:`waveforest.mcrt.trace` like any prepared scene.
    """
    if not isinstance(prototypes, Prototypes):
        raise TypeError(f"prototypes: expected waveforest.mcrt.prepare.Prototypes, got {type(prototypes).__name__}")
    which = np.ascontiguousarray(which, np.int64)
    rot = np.ascontiguousarray(rotation, np.float64)
    t = np.ascontiguousarray(translation, np.float64)
    k = len(which)
    if which.ndim != 1 or k == 0 or rot.shape != (k, 3, 3) or t.shape != (k, 3):
        raise ValueError(f"instances: expected (k,) parts, (k, 3, 3) rotations, (k, 3) translations; got "
                         f"{which.shape}, {rot.shape}, {t.shape}")
    if which.min() < 0 or which.max() >= len(prototypes):
        raise ValueError(f"which: part index outside [0, {len(prototypes)})")
    if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(t))):
        raise ValueError("rotation, translation: non-finite values")
    if (np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max() > 1e-6
            or np.abs(np.linalg.det(rot) - 1.0).max() > 1e-6):
        raise ValueError("rotation: expected orthonormal matrices of determinant +1")
    if quality not in QUALITIES:
        raise ValueError(f"quality: expected one of {', '.join(QUALITIES)}, got {quality!r}")
    parts = prototypes.scenes
    for p in parts:
        if not isinstance(p.intersector, DirectEmbreeIntersector):
            raise ValueError("prototypes: instances need parts prepared with the embree backend")
    # box of each copy: its part's internal box corners, back to part coordinates, placed
    shifts = np.stack([p.shift for p in parts])[which]
    corners = np.stack([np.stack([[b[i, 0], b[j, 1], b[c, 2]] for i in (0, 1) for j in (0, 1) for c in (0, 1)])
                        for b in (p.bounds for p in parts)])[which] + shifts[:, None, :]
    placed = np.einsum("kab,kcb->kca", rot, corners) + t[:, None, :]
    box = np.stack([placed.reshape(-1, 3).min(axis=0), placed.reshape(-1, 3).max(axis=0)])
    shift = 0.5 * (box[0] + box[1])
    xfm = np.concatenate([rot, (np.einsum("kab,kb->ka", rot, shifts) + t - shift)[:, :, None]], axis=2)
    sizes = np.diff(prototypes.starts)[which]
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    tri_data = np.empty((int(sizes.sum()), prototypes.records.shape[1]))
    _instance_records(prototypes.records, prototypes.starts, which, rot, offsets, tri_data)
    return PreparedScene(
        scene=None,
        intersector=InstancedEmbreeIntersector([p.intersector for p in parts], which, xfm, offsets, quality),
        shift=shift,
        tri_data=tri_data,
        bounds=box - shift,
    )
