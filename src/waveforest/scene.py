"""Scenes: triangle soups with per-triangle optical properties, and their PLY files.

A scene is in local metric coordinates: x east, y north, z up, ground near z = 0 and
the field sample at the origin. Each triangle carries its bi-Lambertian reflectance
``rho`` and transmittance ``tau`` at 1064 nm and an element ``kind``
(0 ground, 1 leaf, 2 wood, 3 other; see :mod:`waveforest.constants`).
The PLY form has one vertex list and faces with the properties ``vertex_indices``,
``rho``, ``tau`` and ``kind``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from plyfile import PlyData

from waveforest.atomic import atomic_path
from waveforest.errors import WaveforestError


class SceneError(WaveforestError):
    """A scene or scene file that cannot be used."""


@dataclass(frozen=True)
class Scene:
    """Triangles with per-triangle optical properties.

    Attributes
    ----------
    triangles : (n, 3, 3) float32, or float64 when given float64, m
        Vertex coordinates; the normal follows the right-hand rule of the vertex order. Meshes
        read from files keep float64: float32 steps are 0.5 m at map-grid coordinates
        (10^6-10^7 m), and :func:`waveforest.mcrt.prepare` shifts to the scene's centre
        before it rounds to float32.
    rho, tau : (n,) float32
        Reflectance and transmittance, 0 <= rho + tau <= 1.
    kind : (n,) uint8
        Element kind per triangle (0 ground, 1 leaf, 2 wood, 3 other).
    """

    triangles: np.ndarray
    rho: np.ndarray
    tau: np.ndarray
    kind: np.ndarray

    def __post_init__(self) -> None:
        tri = np.asarray(self.triangles)
        # writable (read-only inputs copied): the kernels that take a scene's arrays compile once
        tri = np.require(tri, np.float64 if tri.dtype == np.float64 else np.float32, ["C", "W"])
        n = tri.shape[0] if tri.ndim == 3 else -1
        if tri.ndim != 3 or tri.shape[1:] != (3, 3):
            raise SceneError(f"triangles: expected shape (n, 3, 3), got {tri.shape}")
        arrays = {}
        for name, dtype in (("rho", np.float32), ("tau", np.float32), ("kind", np.uint8)):
            a = np.require(np.broadcast_to(getattr(self, name), (n,)), dtype, ["C", "W"])
            arrays[name] = a
        if not np.all(np.isfinite(tri)):
            raise SceneError("triangles: non-finite coordinates")
        rho, tau = arrays["rho"], arrays["tau"]
        if np.any(rho < 0) or np.any(tau < 0) or np.any(rho + tau > 1 + 1e-6):
            raise SceneError("rho, tau: expected rho >= 0, tau >= 0 and rho + tau <= 1")
        if np.any(arrays["kind"] > 3):
            raise SceneError("kind: expected 0 ground, 1 leaf, 2 wood or 3 other")
        object.__setattr__(self, "triangles", tri)
        for name, a in arrays.items():
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return self.triangles.shape[0]

    @property
    def normals(self) -> np.ndarray:
        """(n, 3) float64 unit normals (right-hand rule of the vertex order)."""
        t = self.triangles.astype(np.float64)
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        norm = np.linalg.norm(n, axis=1, keepdims=True)
        return n / np.where(norm > 0, norm, 1.0)

    @property
    def areas(self) -> np.ndarray:
        """(n,) float64 one-sided triangle areas, m^2."""
        t = self.triangles.astype(np.float64)
        return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)

    @property
    def bounds(self) -> np.ndarray:
        """(2, 3) float64 axis-aligned bounding box [min, max], m."""
        v = self.triangles.reshape(-1, 3)
        return np.stack([v.min(axis=0), v.max(axis=0)]).astype(np.float64)

    def translated(self, offset) -> Scene:
        """The scene moved by ``offset`` (3,), m."""
        off = np.asarray(offset, dtype=self.triangles.dtype).reshape(1, 1, 3)
        return Scene(self.triangles + off, self.rho, self.tau, self.kind)

    def subset(self, mask) -> Scene:
        """The triangles selected by a boolean mask or index array."""
        return Scene(self.triangles[mask], self.rho[mask], self.tau[mask], self.kind[mask])

    @staticmethod
    def concat(scenes: list[Scene]) -> Scene:
        """One scene holding the triangles of all ``scenes``, in order."""
        if not scenes:
            raise SceneError("concat: no scenes")
        return Scene(
            np.concatenate([s.triangles for s in scenes]),
            np.concatenate([s.rho for s in scenes]),
            np.concatenate([s.tau for s in scenes]),
            np.concatenate([s.kind for s in scenes]),
        )


PLY_COMMENT = "waveforest scene: face rho, tau (1064 nm), kind 0 ground 1 leaf 2 wood 3 other"

PLY_FACE = np.dtype([("n", "u1"), ("vertex_indices", "<i4", (3,)), ("rho", "<f4"), ("tau", "<f4"),
                     ("kind", "u1")])
"""One face record of :func:`write_ply`, packed as the header declares it."""


def write_ply(scene: Scene, path: str | Path) -> Path:
    """Write ``scene`` as a binary little-endian PLY (faces carry rho, tau, kind).

    One vertex per triangle corner (3n vertices, float32 x y z) and n faces
    (``list uchar int vertex_indices``, float ``rho``, float ``tau``, uchar ``kind``), written
    as two packed arrays: the file plyfile writes, without its per-row loop.
    """

    n = len(scene)
    faces = np.empty(n, dtype=PLY_FACE)
    faces["n"] = 3
    faces["vertex_indices"] = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    faces["rho"], faces["tau"], faces["kind"] = scene.rho, scene.tau, scene.kind
    header = "\n".join([
        "ply", "format binary_little_endian 1.0", f"comment {PLY_COMMENT}",
        f"element vertex {3 * n}", "property float x", "property float y", "property float z",
        f"element face {n}", "property list uchar int vertex_indices", "property float rho",
        "property float tau", "property uchar kind", "end_header", "",
    ])
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(scene.triangles.astype("<f4", copy=False).tobytes())
        fh.write(faces.tobytes())
    return path


def fan_triangles(flat: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Polygons fanned from their first vertex: ``flat`` (sum n,) vertex indices of polygons of
    ``n`` (p,) >= 3 vertices each, in order -> (triangles (sum(n - 2), 3) as (v0, vk, vk+1),
    the polygon of each triangle (sum(n - 2),))."""
    starts = np.concatenate([[0], np.cumsum(n)[:-1]]).astype(np.int64)
    owner = np.repeat(np.arange(len(n)), n - 2)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(n - 2) - (n - 2), n - 2)
    first = starts[owner]
    return np.stack([flat[first], flat[first + k + 1], flat[first + k + 2]], axis=1), owner


def read_ply(path: str | Path, default: tuple[float, float, int] | None = None) -> Scene:
    """Read a PLY whose faces carry ``rho``, ``tau`` and ``kind`` (polygons are fanned).

    A PLY without them (a mesh from any other tool) takes ``default`` (rho, tau, kind) for
    every face when it is given; else SceneError.
    """

    path = Path(path)
    if not path.exists():
        raise SceneError(f"{path}: no such file")
    try:
        try:  # fast path: triangle faces (what write_ply produces)
            ply = PlyData.read(str(path), known_list_len={"face": {"vertex_indices": 3}})
        except Exception:  # polygons of any size, or another list name
            ply = PlyData.read(str(path))
        vert = ply["vertex"].data
        face = ply["face"].data
    except Exception as exc:  # plyfile raises several types for malformed files
        raise SceneError(f"{path}: not a readable PLY with vertex and face elements ({exc})") from exc
    names = face.dtype.names or ()
    missing = [p for p in ("rho", "tau", "kind") if p not in names]
    if missing and default is None:
        raise SceneError(f"{path}: face property {', '.join(missing)} missing (expected rho, tau, kind)")
    idx_name = "vertex_indices" if "vertex_indices" in names else "vertex_index"
    if idx_name not in names:
        raise SceneError(f"{path}: faces have no vertex_indices")
    xyz = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
    polys = face[idx_name]
    if polys.dtype != object and polys.ndim == 2 and polys.shape[1] == 3:
        idx = polys.astype(np.int64)
        owner = np.arange(len(idx))
    else:  # variable-length polygons: fan-triangulated, (v0, vk, vk+1)
        n = np.fromiter((len(p) for p in polys), np.int64, len(polys))
        if n.size and n.min() < 3:
            raise SceneError(f"{path}: a face with fewer than 3 vertices")
        flat = np.concatenate([np.asarray(p, np.int64) for p in polys]) if len(polys) else np.zeros(0, np.int64)
        idx, owner = fan_triangles(flat, n)
    if idx.size and (idx.min() < 0 or idx.max() >= len(xyz)):
        raise SceneError(f"{path}: face vertex index out of range (0..{len(xyz) - 1})")
    if missing:
        rho, tau, kind = default
        return Scene(xyz[idx], np.float32(rho), np.float32(tau), np.uint8(kind))
    return Scene(xyz[idx], face["rho"][owner], face["tau"][owner], face["kind"][owner])
