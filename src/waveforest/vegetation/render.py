"""PNG pictures of a scene (like Fig. 5 of Hovi & Korpela 2014): side view and top view.

Triangles are projected orthographically and rasterised with a depth buffer (a Numba kernel,
2 x 2 samples per pixel), coloured by element kind and shaded by how much each triangle faces
the viewer; matplotlib draws the axes around the two images.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numba import njit

from waveforest.constants import KIND_GROUND, KIND_LEAF, KIND_OTHER, KIND_WOOD
from waveforest.plotting import pyplot, save_png
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

SUPERSAMPLE = 2
"""Samples per pixel along each axis (their mean is the pixel's colour and coverage)."""


def _colours(scene: Scene, view: np.ndarray) -> np.ndarray:
    base = np.array([KIND_COLOURS[int(k)] for k in range(4)])[scene.kind]
    facing = np.abs(scene.normals @ view)
    return np.clip(base * (SHADE_MIN + (1 - SHADE_MIN) * facing)[:, None], 0, 1)


@njit(cache=True, nogil=True)
def rasterise(uv, depth, colour, lo, step, width, height):
    """Nearest-triangle image of projected triangles.

    ``uv`` (n, 3, 2) image-plane coordinates, m; ``depth`` (n,) distance from the viewer of
    each triangle (its centroid); ``colour`` (n, 3) RGB in [0, 1]; ``lo`` (2,) coordinates of
    the image's lower-left corner, ``step`` m per sample. Returns (height, width, 4) RGBA,
    row 0 at the top; a sample is covered where its centre lies inside a triangle
    (edge functions, either winding).
    """
    img = np.zeros((height, width, 4))
    zbuf = np.full((height, width), np.inf)
    for k in range(uv.shape[0]):
        x0, y0 = (uv[k, 0, 0] - lo[0]) / step, (uv[k, 0, 1] - lo[1]) / step
        x1, y1 = (uv[k, 1, 0] - lo[0]) / step, (uv[k, 1, 1] - lo[1]) / step
        x2, y2 = (uv[k, 2, 0] - lo[0]) / step, (uv[k, 2, 1] - lo[1]) / step
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if area == 0.0:
            continue
        sgn = 1.0 if area > 0.0 else -1.0
        i_lo = max(0, int(np.floor(min(x0, x1, x2) - 0.5)))
        i_hi = min(width - 1, int(np.ceil(max(x0, x1, x2) - 0.5)))
        j_lo = max(0, int(np.floor(min(y0, y1, y2) - 0.5)))
        j_hi = min(height - 1, int(np.ceil(max(y0, y1, y2) - 0.5)))
        for j in range(j_lo, j_hi + 1):
            py = j + 0.5
            for i in range(i_lo, i_hi + 1):
                px = i + 0.5
                e0 = sgn * ((x1 - x0) * (py - y0) - (y1 - y0) * (px - x0))
                e1 = sgn * ((x2 - x1) * (py - y1) - (y2 - y1) * (px - x1))
                e2 = sgn * ((x0 - x2) * (py - y2) - (y0 - y2) * (px - x2))
                if e0 < 0.0 or e1 < 0.0 or e2 < 0.0 or depth[k] >= zbuf[j, i]:
                    continue
                zbuf[j, i] = depth[k]
                r = height - 1 - j
                img[r, i, 0], img[r, i, 1], img[r, i, 2] = colour[k, 0], colour[k, 1], colour[k, 2]
                img[r, i, 3] = 1.0
    return img


def _view_image(ax, uv: np.ndarray, depth: np.ndarray, colour: np.ndarray) -> None:
    """Draw the rasterised triangles into ``ax`` over its current limits, one image pixel per
    screen pixel (after layout)."""
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    box = ax.get_window_extent()
    w, h = max(1, int(round(box.width))), max(1, int(round(box.height)))
    step = max((x1 - x0) / w, (y1 - y0) / h) / SUPERSAMPLE
    ws, hs = w * SUPERSAMPLE, h * SUPERSAMPLE
    img = rasterise(np.ascontiguousarray(uv, np.float64), np.ascontiguousarray(depth, np.float64),
                     np.ascontiguousarray(colour, np.float64), np.array([x0, y0]), step, ws, hs)
    img = img.reshape(h, SUPERSAMPLE, w, SUPERSAMPLE, 4).mean(axis=(1, 3))
    cover = img[..., 3:]
    img[..., :3] = np.where(cover > 0, img[..., :3] / np.maximum(cover, 1e-12), 1.0)
    ax.imshow(img, extent=(x0, x0 + w * SUPERSAMPLE * step, y0, y0 + h * SUPERSAMPLE * step),
              origin="upper", interpolation="nearest", zorder=1)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)


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
    plt = pyplot()
    tri = scene.triangles.astype(np.float64)
    lo, hi = scene.bounds
    fig, (ax_s, ax_t) = plt.subplots(1, 2, figsize=(11, 5.2), dpi=dpi,
                                     gridspec_kw={"width_ratios": [1.0, 1.0]})
    side = scene.kind != KIND_GROUND
    g = ~side
    if np.any(g):  # the ground as a band under the side view
        zg = tri[g][:, :, 2]
        ax_s.axhspan(float(zg.min()) - 0.02, float(zg.max()), color=KIND_COLOURS[KIND_GROUND], zorder=0)
    for ax, ylabel in ((ax_s, "z (m)"), (ax_t, "y (m)")):
        ax.set_xlim(lo[0], hi[0])
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel(ylabel)
    ax_s.set_ylim(min(lo[2], 0.0) - 0.05, max(hi[2], 0.1) * 1.05)
    ax_t.set_ylim(lo[1], hi[1])
    ax_s.set_title("side view")
    ax_t.set_title("top view")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.canvas.draw()  # the axes' final boxes, in screen pixels
    # side view looking along +y (nearest: smallest y); top view looking down (nearest: highest z)
    ts = tri[side]
    _view_image(ax_s, ts[:, :, [0, 2]], ts[:, :, 1].mean(axis=1),
                _colours(scene.subset(side), np.array([0.0, 1.0, 0.0])))
    _view_image(ax_t, tri[:, :, :2], -tri[:, :, 2].mean(axis=1), _colours(scene, np.array([0.0, 0.0, 1.0])))
    return save_png(fig, path, dpi=dpi)
