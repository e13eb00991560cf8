"""PNG pictures of a scene (like Fig. 5 of Hovi & Korpela 2014): side view and top view.

Triangles are projected orthographically and drawn back to front (painter's algorithm) as
one matplotlib ``PolyCollection`` per view, coloured by element kind and shaded by how much
each triangle faces the viewer.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from waveforest.atomic import atomic_path
from waveforest.constants import KIND_GROUND, KIND_LEAF, KIND_OTHER, KIND_WOOD
from waveforest.plotting import pyplot
from waveforest.scene import Scene

KIND_COLOURS = {
    KIND_GROUND: (0.62, 0.55, 0.45),
    KIND_LEAF: (0.25, 0.55, 0.20),
    KIND_WOOD: (0.45, 0.30, 0.18),
    KIND_OTHER: (0.70, 0.70, 0.62),
}
"""RGB colour of each element kind."""

SHADE_MIN = 0.45
"""Brightness of a triangle seen edge-on (1 = facing the viewer)."""


def _colours(scene: Scene, view: np.ndarray) -> np.ndarray:
    base = np.array([KIND_COLOURS[int(k)] for k in range(4)])[scene.kind]
    facing = np.abs(scene.normals @ view)
    return np.clip(base * (SHADE_MIN + (1 - SHADE_MIN) * facing)[:, None], 0, 1)


def render_png(scene: Scene, path: str | Path, title: str = "", dpi: int = 120) -> Path:
    """Write a side view (x-z, looking north) and a top view (x-y) of ``scene`` as a PNG.

    Parameters
    ----------
    scene : Scene
    path : str or Path
        Output file (written atomically).
    title : str
        Figure title.
    dpi : int
        Resolution.

    Returns
    -------
    Path
    """
    from matplotlib.collections import PolyCollection

    plt = pyplot()

    tri = scene.triangles
    lo, hi = scene.bounds
    fig, (ax_s, ax_t) = plt.subplots(1, 2, figsize=(11, 5.2),
                                     gridspec_kw={"width_ratios": [1.0, 1.0]})
    # side view, looking along +y: far (large y) first; the ground as a band
    side = scene.kind != KIND_GROUND
    order = np.argsort(-tri[side, :, 1].mean(axis=1), kind="stable")
    t_side = tri[side][order]
    ax_s.add_collection(PolyCollection(t_side[:, :, [0, 2]], facecolors=_colours(scene.subset(side), np.array([0.0, 1.0, 0.0]))[order],
                                       edgecolors="none", antialiased=False))
    g = scene.kind == KIND_GROUND
    if np.any(g):
        zg = tri[g][:, :, 2]
        ax_s.axhspan(float(zg.min()) - 0.02, float(zg.max()), color=KIND_COLOURS[KIND_GROUND], zorder=0)
    ax_s.set_xlim(lo[0], hi[0])
    ax_s.set_ylim(min(lo[2], 0.0) - 0.05, max(hi[2], 0.1) * 1.05)
    ax_s.set_aspect("equal")
    ax_s.set_xlabel("x (m)")
    ax_s.set_ylabel("z (m)")
    ax_s.set_title("side view")
    # top view: low first
    order = np.argsort(tri[:, :, 2].mean(axis=1), kind="stable")
    ax_t.add_collection(PolyCollection(tri[order][:, :, :2], facecolors=_colours(scene, np.array([0.0, 0.0, 1.0]))[order],
                                       edgecolors="none", antialiased=False))
    ax_t.set_xlim(lo[0], hi[0])
    ax_t.set_ylim(lo[1], hi[1])
    ax_t.set_aspect("equal")
    ax_t.set_xlabel("x (m)")
    ax_t.set_ylabel("y (m)")
    ax_t.set_title("top view")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    plt.close(fig)
    return path
