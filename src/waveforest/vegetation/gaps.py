"""Leaf area index and the nadir gap fraction of a scene (independent of the MCRT engine).

LAI is the one-sided area of the leaf triangles (kind 1) per plot area (36 m^2). The nadir
gap fraction is the share of points of a regular grid, over a square region, that no
triangle of the chosen kinds covers in vertical projection: the probability that a vertical
ray reaches the ground. For a random canopy of leaf area index L it is exp(-G(0) L) with
G from the LAD (Nilson 1971; :meth:`LeafAngleDistribution.g`); clumping of leaves on shoots
raises it. The coverage grid also gives gap sizes.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from waveforest.constants import KIND_LEAF, KIND_OTHER, KIND_WOOD
from waveforest.scene import Scene
from waveforest.vegetation.params import PLOT_AREA_M2

GAP_CELL_M = 0.01
"""Default grid spacing of the coverage raster, m."""

GAP_EXTENT_M = 2.5
"""Default half-side of the gap-fraction region, m (inside the plot edge band)."""


def leaf_area_index(scene: Scene, plot_area: float = PLOT_AREA_M2) -> float:
    """One-sided area of the leaf triangles (kind 1) per ground area."""
    return float(scene.areas[scene.kind == KIND_LEAF].sum() / plot_area)


@njit(cache=True, nogil=True)
def coverage_kernel(tri_xy, x0, y0, cell, nx, ny):  # pragma: no cover - compiled; tested against reference
    """Grid points (centres x0 + (i + 1/2) cell, y0 + (j + 1/2) cell) inside any triangle."""
    out = np.zeros((ny, nx), dtype=np.bool_)
    for t in range(tri_xy.shape[0]):
        ax, ay = tri_xy[t, 0, 0], tri_xy[t, 0, 1]
        bx, by = tri_xy[t, 1, 0], tri_xy[t, 1, 1]
        cx, cy = tri_xy[t, 2, 0], tri_xy[t, 2, 1]
        area2 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if area2 == 0.0:
            continue
        s = 1.0 if area2 > 0 else -1.0
        i0 = max(int(np.floor((min(ax, bx, cx) - x0) / cell - 0.5)), 0)
        i1 = min(int(np.ceil((max(ax, bx, cx) - x0) / cell - 0.5)), nx - 1)
        j0 = max(int(np.floor((min(ay, by, cy) - y0) / cell - 0.5)), 0)
        j1 = min(int(np.ceil((max(ay, by, cy) - y0) / cell - 0.5)), ny - 1)
        for j in range(j0, j1 + 1):
            py = y0 + (j + 0.5) * cell
            for i in range(i0, i1 + 1):
                if out[j, i]:
                    continue
                px = x0 + (i + 0.5) * cell
                e0 = s * ((bx - ax) * (py - ay) - (by - ay) * (px - ax))
                e1 = s * ((cx - bx) * (py - by) - (cy - by) * (px - bx))
                e2 = s * ((ax - cx) * (py - cy) - (ay - cy) * (px - cx))
                if e0 >= 0.0 and e1 >= 0.0 and e2 >= 0.0:
                    out[j, i] = True
    return out


def nadir_coverage(scene: Scene, kinds=(KIND_LEAF, KIND_WOOD, KIND_OTHER), cell_m: float = GAP_CELL_M,
                   extent_m: float = GAP_EXTENT_M) -> np.ndarray:
    """Which grid points the vertical projection of the chosen triangles covers.

    Parameters
    ----------
    scene : Scene
    kinds : sequence of int
        Element kinds that block a vertical ray (default: everything but the ground).
    cell_m : float, m
        Grid spacing (> 0).
    extent_m : float, m
        Half-side of the square region centred on the origin (> 0).

    Returns
    -------
    (ny, nx) bool
        True where covered; row j, column i is the point
        (-extent + (i + 1/2) cell, -extent + (j + 1/2) cell).
    """
    if not (cell_m > 0 and extent_m > 0):
        raise ValueError(f"nadir_coverage: cell_m and extent_m must be > 0, got {cell_m}, {extent_m}")
    n = int(round(2 * extent_m / cell_m))
    if n < 1:
        raise ValueError("nadir_coverage: extent smaller than one cell")
    sel = np.isin(scene.kind, np.asarray(kinds, dtype=np.uint8))
    tri_xy = np.ascontiguousarray(scene.triangles[sel][:, :, :2], dtype=np.float64)
    return coverage_kernel(tri_xy, -float(extent_m), -float(extent_m), float(cell_m), n, n)


def nadir_gap_fraction(scene: Scene, kinds=(KIND_LEAF, KIND_WOOD, KIND_OTHER),
                       cell_m: float = GAP_CELL_M, extent_m: float = GAP_EXTENT_M) -> float:
    """Fraction of vertical lines of sight over the region that reach the ground."""
    return float(1.0 - nadir_coverage(scene, kinds, cell_m, extent_m).mean())
