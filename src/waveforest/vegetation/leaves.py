"""Leaf outlines (polygons in ``resources/vegetation/outlines/``) and batched leaf placement.

An outline is a simple counter-clockwise polygon in units of the leaf length: x along the
midrib from the leaf base (petiole junction) to the tip, y across. It is triangulated once by
ear clipping; every leaf of a scene is that template scaled and rotated, all leaves at once:

    vertex = base + L (x m + w y b)

with L the leaf length, w a width factor, m the midrib direction and b = n x m, so that the
right-hand normal of each triangle is the sampled leaf normal n. The midrib is the
direction ``toward`` (e.g. away from the stem) projected on the leaf plane: the leaf normal
keeps the sampled inclination and azimuth exactly (docs/method.md §(g)) while the blade points away
from where it is attached.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pandas as pd
from numba import njit

from waveforest.vegetation.params import RES, ParameterFileError

_PARALLEL_EPS = 1e-9
"""|toward x normal| below this means ``toward`` is parallel to the normal (fallback frame)."""


def polygon_area(xy: np.ndarray) -> float:
    """Signed area of a polygon (shoelace), positive for counter-clockwise vertices."""
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def _cross2(o, a, b) -> float:
    return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])


def triangulate(xy: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation of a simple counter-clockwise polygon.

    Parameters
    ----------
    xy : (m, 3 <= m) float64
        Vertices, counter-clockwise, no repeated closing vertex.

    Returns
    -------
    (m - 2, 3) int64
        Vertex indices of counter-clockwise triangles tiling the polygon.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 3:
        raise ValueError(f"triangulate: expected (m >= 3, 2) vertices, got {xy.shape}")
    if polygon_area(xy) <= 0:
        raise ValueError("triangulate: polygon must be counter-clockwise with positive area")
    idx = list(range(len(xy)))
    tris = []
    while len(idx) > 3:
        for k in range(len(idx)):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = xy[i0], xy[i1], xy[i2]
            if _cross2(a, b, c) <= 0:  # reflex or degenerate corner: not an ear
                continue
            others = [j for j in idx if j not in (i0, i1, i2)]
            if any(_cross2(a, b, xy[j]) >= 0 and _cross2(b, c, xy[j]) >= 0
                   and _cross2(c, a, xy[j]) >= 0 for j in others):
                continue
            tris.append((i0, i1, i2))
            idx.pop(k)
            break
        else:
            raise ValueError("triangulate: polygon is not simple (no ear found)")
    tris.append(tuple(idx))
    return np.asarray(tris, dtype=np.int64)


@dataclass(frozen=True)
class Outline:
    """A triangulated leaf outline.

    Attributes
    ----------
    name : str
    vertices : (m, 2) float64
        Polygon in units of the leaf length (x from 0 to 1).
    triangles : (T, 3, 2) float64
        Its counter-clockwise triangulation.
    area : float
        Polygon area for unit length and width factor 1.
    width : float
        Width (y extent) for unit length.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    area: float
    width: float

    @property
    def n_triangles(self) -> int:
        return self.triangles.shape[0]

    def width_factor(self, length_width: float) -> float:
        """Factor on y giving a leaf of the given length/width ratio (0 = own proportions)."""
        return 1.0 if length_width <= 0 else 1.0 / (length_width * self.width)

    def length_for_area(self, area, width_factor=1.0) -> np.ndarray:
        """Leaf length giving one-sided ``area`` (m^2) at a width factor, m."""
        return np.sqrt(np.asarray(area, dtype=np.float64) / (self.area * width_factor))


@functools.cache
def load_outline(name: str) -> Outline:
    """The outline ``outlines/<name>.csv`` (columns x, y; '#' comment lines give the source)."""
    path = RES / "outlines" / f"{name}.csv"
    if not path.exists():
        raise ParameterFileError(f"{path}: no leaf outline named {name!r}")
    df = pd.read_csv(path, comment="#")
    if list(df.columns) != ["x", "y"]:
        raise ParameterFileError(f"{path}: expected columns x, y")
    xy = df.to_numpy(dtype=np.float64)
    if not np.all(np.isfinite(xy)) or xy[:, 0].min() < 0 or abs(xy[:, 0].max() - 1.0) > 1e-12:
        raise ParameterFileError(f"{path}: x must run from 0 to 1 (units of the leaf length)")
    try:
        tri_idx = triangulate(xy)
    except ValueError as exc:
        raise ParameterFileError(f"{path}: {exc}") from None
    return Outline(
        name=name,
        vertices=xy,
        triangles=xy[tri_idx],
        area=polygon_area(xy),
        width=float(xy[:, 1].max() - xy[:, 1].min()),
    )


def leaf_frames(normal: np.ndarray, toward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midrib and cross directions of leaves with the given normals.

    Parameters
    ----------
    normal : (n, 3) float64
        Unit leaf normals.
    toward : (n, 3) float64
        Directions the leaves should point to (not necessarily unit); the midrib is their
        projection on the leaf plane. Where ``toward`` is parallel to the normal, any
        in-plane direction is used.

    Returns
    -------
    m, b : (n, 3) float64
        Unit midrib and cross directions; (m, b, normal) is right-handed orthonormal.
    """
    return _frames_kernel(np.require(normal, np.float64, ["C", "W"]), np.require(toward, np.float64, ["C", "W"]))


@njit(cache=True, nogil=True)
def _frames_kernel(n, t):  # pragma: no cover - compiled; tested against the NumPy expressions
    """:func:`leaf_frames` leaf by leaf, with NumPy's order of operations (bit for bit:
    the projection t - (t . n) n, its norm, the fallback axis, m / |m|, b = n x m)."""
    k = n.shape[0]
    m = np.empty((k, 3))
    b = np.empty((k, 3))
    for i in range(k):
        n0, n1, n2 = n[i, 0], n[i, 1], n[i, 2]
        t0, t1, t2 = t[i, 0], t[i, 1], t[i, 2]
        d = t0 * n0 + t1 * n1 + t2 * n2
        m0, m1, m2 = t0 - d * n0, t1 - d * n1, t2 - d * n2
        norm = np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        if norm < _PARALLEL_EPS * max(np.sqrt(t0 * t0 + t1 * t1 + t2 * t2), 1.0):  # any axis not parallel to n
            a0, a1 = (1.0, 0.0) if abs(n0) < 0.9 else (0.0, 1.0)
            d = a0 * n0 + a1 * n1 + 0.0 * n2
            m0, m1, m2 = a0 - d * n0, a1 - d * n1, 0.0 - d * n2
            norm = np.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
        m0, m1, m2 = m0 / norm, m1 / norm, m2 / norm
        m[i, 0], m[i, 1], m[i, 2] = m0, m1, m2
        b[i, 0], b[i, 1], b[i, 2] = n1 * m2 - n2 * m1, n2 * m0 - n0 * m2, n0 * m1 - n1 * m0
    return m, b


@njit(cache=True, nogil=True)
def _place_kernel(base, m, b, length, wf, tx, ty):  # pragma: no cover - compiled; tested against reference
    """vertex[i, t, v] = base[i] + length[i] (tx[t, v] m[i] + wf[i] ty[t, v] b[i]), float32."""
    n = base.shape[0]
    nt = tx.shape[0]
    out = np.empty((n * nt, 3, 3), dtype=np.float32)
    for i in range(n):
        lm0, lm1, lm2 = length[i] * m[i, 0], length[i] * m[i, 1], length[i] * m[i, 2]
        lw = length[i] * wf[i]
        lb0, lb1, lb2 = lw * b[i, 0], lw * b[i, 1], lw * b[i, 2]
        for t in range(nt):
            row = i * nt + t
            for v in range(3):
                x, y = tx[t, v], ty[t, v]
                out[row, v, 0] = base[i, 0] + x * lm0 + y * lb0
                out[row, v, 1] = base[i, 1] + x * lm1 + y * lb1
                out[row, v, 2] = base[i, 2] + x * lm2 + y * lb2
    return out


def place_leaves(outline: Outline, base, normal, toward, length, width_factor=1.0) -> np.ndarray:
    """Triangles of leaves placed and oriented in the scene, all at once.

    Parameters
    ----------
    outline : Outline
    base : (n, 3) float64, m
        Leaf base (x = 0 of the outline) positions.
    normal : (n, 3) float64
        Unit leaf normals (the triangles' right-hand normals).
    toward : (n, 3) float64
        Directions the leaves point to (see :func:`leaf_frames`).
    length : (n,) float64, m
        Leaf lengths.
    width_factor : float or (n,) float64
        Factor on the outline's y coordinates.

    Returns
    -------
    (n * T, 3, 3) float32, m
        Triangles, leaf by leaf (T = ``outline.n_triangles``). Leaf areas are
        ``outline.area * length**2 * width_factor``.
    """
    base = np.ascontiguousarray(base, dtype=np.float64)
    if base.ndim != 2 or base.shape[1] != 3:
        raise ValueError(f"place_leaves: base must be (n, 3), got {base.shape}")
    n = base.shape[0]
    if np.shape(normal) != (n, 3) or np.shape(toward) != (n, 3):
        raise ValueError("place_leaves: base, normal and toward must all be (n, 3)")
    length = np.require(np.broadcast_to(np.asarray(length, dtype=np.float64), (n,)), requirements=["C", "W"])
    wf = np.require(np.broadcast_to(np.asarray(width_factor, dtype=np.float64), (n,)), requirements=["C", "W"])
    if np.any(~np.isfinite(length)) or np.any(length < 0) or np.any(wf < 0):
        raise ValueError("place_leaves: lengths and width factors must be finite and >= 0")
    m, b = leaf_frames(normal, toward)
    tx = np.ascontiguousarray(outline.triangles[..., 0])
    ty = np.ascontiguousarray(outline.triangles[..., 1])
    return _place_kernel(base, m, b, length, wf, tx, ty)


def crossed_planes(outline: Outline, base, normal, toward, length, width_factor=1.0) -> np.ndarray:
    """Needle-shoot elements: two planes crossing along the shoot axis.

    The first plane has the sampled ``normal`` and holds the axis (``toward`` projected on
    it); the second holds the axis and is perpendicular to the first (normal flipped to
    the upper hemisphere). Each plane is ``outline`` (centred on the axis, e.g. a rectangle).

    Returns
    -------
    (2 n T, 3, 3) float32, m
        The first planes of all shoots, then the second planes.
    """
    normal = np.asarray(normal, dtype=np.float64)
    m, b = leaf_frames(normal, toward)
    n2 = np.where(b[:, 2:3] >= 0, b, -b)
    first = place_leaves(outline, base, normal, m, length, width_factor)
    second = place_leaves(outline, base, n2, m, length, width_factor)
    return np.concatenate([first, second])
