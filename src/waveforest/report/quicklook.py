"""Figures and the HTML page of ``waveforest quicklook`` and the plot of ``tune-cfd``.

A rendering library (docs/design.md): it draws what the stages hand it and reads no file.
The page is one self-contained HTML file: figures are embedded as PNG data URIs, so it can be
mailed or opened anywhere.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from waveforest.atomic import atomic_path
from waveforest.plotting import pyplot, save_png
from waveforest.sensor.cfd_tuning import WIDTH_EDGES
from waveforest.sensor.params import CFD_CHECK_M, RANGE_GATE_M

PLOT_POINTS = 20_000
"""Most pulses drawn in a scatter plot (a seeded random subset beyond that)."""


def _subset(n: int, k: int, seed: int) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(np.random.default_rng([int(seed), 0x9107]).choice(n, size=k, replace=False))


def cfd_residual_figure(amplitude, width_rel, residual_m, ok, correction, *, title: str = "", seed: int = 0):
    """Two panels: residual (DR - corrected CFD range, m) against the CFD echo amplitude and
    against the first echo's FWHM in system pulse widths, with the 0.10-m band and the
    width-class edges; the range correction that was subtracted is drawn on the first."""
    plt = pyplot()
    idx = np.flatnonzero(np.asarray(ok))
    idx = idx[_subset(idx.size, PLOT_POINTS, seed)]
    a, w, r = (np.asarray(v, dtype=np.float64)[idx] for v in (amplitude, width_rel, residual_m))
    r = np.clip(r, -RANGE_GATE_M, RANGE_GATE_M)
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, x, label in ((axes[0], a, "CFD echo amplitude above the noise mean, DN"),
                         (axes[1], w, "first-echo FWHM / system pulse FWHM")):
        inside = np.abs(r) < CFD_CHECK_M
        ax.scatter(x[inside], r[inside], s=3, alpha=0.35, color="tab:blue", lw=0, label="within 0.10 m")
        ax.scatter(x[~inside], r[~inside], s=3, alpha=0.5, color="tab:red", lw=0, label="outside (clipped at ±1 m)")
        for y in (-CFD_CHECK_M, CFD_CHECK_M):
            ax.axhline(y, color="k", lw=0.8, ls="--")
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    if np.isfinite(a).any() and np.nanmax(a) > 0:
        axes[0].set_xscale("log")
        grid = np.geomspace(max(np.nanmin(a[a > 0]), 1e-3), np.nanmax(a), 200)
        axes[0].plot(grid, correction(grid), color="tab:green", lw=1.5, label="range correction (subtracted)")
    for e in WIDTH_EDGES:
        axes[1].axvline(e, color="0.4", lw=0.8, ls=":")
    axes[0].set_ylabel("DR range - corrected CFD range, m")
    axes[0].set_ylim(-0.5, 0.5)
    axes[0].legend(loc="lower right", fontsize=8, markerscale=3)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_cfd_residuals(amplitude, width_rel, residual_m, ok, correction, path, *, title: str = "", seed: int = 0) -> Path:
    """:func:`cfd_residual_figure` written as a PNG (atomically)."""
    return save_png(cfd_residual_figure(amplitude, width_rel, residual_m, ok, correction, title=title, seed=seed),
                    path, dpi=110)


def gallery_figure(waveforms: Sequence[dict], noise_mean: float, arming_level: float, *, cols: int = 3):
    """Waveforms with their DR echoes (red dashed) and CFD echoes (green solid, range-corrected).

    Each item: ``t_ns`` (n,), ``samples`` (n,), ``dr_ns`` (list), ``cfd_ns`` (list), ``label``.
    """
    plt = pyplot()
    n = max(len(waveforms), 1)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.0 * cols, 2.4 * rows), squeeze=False)
    for ax in axes.ravel()[len(waveforms):]:
        ax.set_visible(False)
    for ax, w in zip(axes.ravel(), waveforms):
        ax.plot(w["t_ns"], w["samples"], color="0.2", lw=0.9, drawstyle="steps-mid")
        ax.axhline(noise_mean, color="0.6", lw=0.6)
        ax.axhline(arming_level, color="0.6", lw=0.6, ls=":")
        for t in w["dr_ns"]:
            ax.axvline(t, color="tab:red", lw=1.0, ls="--")
        for t in w["cfd_ns"]:
            ax.axvline(t, color="tab:green", lw=1.0)
        ax.set_title(w["label"], fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time from the first sample, ns", fontsize=8)
    fig.tight_layout()
    return fig


def histogram_figure(hists: dict):
    """One panel per feature: ``hists[name] = (counts, edges, n_nan)``."""
    plt = pyplot()
    k = max(len(hists), 1)
    fig, axes = plt.subplots(1, k, figsize=(3.3 * k, 2.8), squeeze=False)
    for ax, (name, (counts, edges, n_nan)) in zip(axes[0], hists.items()):
        ax.stairs(counts, edges, fill=True, color="tab:blue", alpha=0.7)
        ax.set_title(f"{name} ({int(counts.sum()):,} pulses; {n_nan:,} none)", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return fig


def map_figure(grid: np.ndarray, extent: tuple[float, float, float, float], name: str):
    """Mean of a feature per cell over the file's extent (x right, y up; NaN cells blank)."""
    plt = pyplot()
    x0, x1, y0, y1 = extent
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    fig, ax = plt.subplots(figsize=(7, max(3.0, min(9.0, 7 * aspect))))
    finite = grid[np.isfinite(grid)]
    lo, hi = (np.percentile(finite, [2, 98]) if finite.size else (0, 1))
    im = ax.imshow(grid, origin="lower", extent=extent, vmin=lo, vmax=hi, cmap="viridis", interpolation="nearest")
    fig.colorbar(im, ax=ax, label=f"mean first-echo {name}")
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    ax.ticklabel_format(useOffset=False, style="plain")
    fig.tight_layout()
    return fig


def figure_uri(fig) -> str:
    """A figure as a PNG data URI (the figure is closed)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    pyplot().close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _table(rows: Sequence[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows) + "</table>"


_STYLE = """body{font-family:system-ui,sans-serif;max-width:1150px;margin:2em auto;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:0.9em}th,td{padding:2px 10px;text-align:left;border-bottom:1px solid #eee}
th{font-weight:600}pre{background:#f6f6f6;padding:0.8em;overflow-x:auto;font-size:0.8em}
img{max-width:100%}.ok{color:#176317;font-weight:600}.miss{color:#a0241c;font-weight:600}
p.note{background:#f3f6fb;padding:0.6em 0.9em;border-left:4px solid #4a78b5}"""


def write_page(path, *, title: str, summary_text: str, facts: Sequence[tuple[str, str]], agreement_rows,
               verdict: str, passed: bool, note: str, figures: dict[str, str], files: Sequence[tuple[str, str]]) -> Path:
    """Write the quicklook page (atomically).

    ``figures``: section name -> data URI (``cfd``, ``gallery``, ``histograms``, ``map``).
    ``files``: (name, what) of the outputs beside the page.
    """
    esc = html.escape
    img = lambda key, alt: (f'<img src="{figures[key]}" alt="{esc(alt)}">' if key in figures else  # noqa: E731
                            "<p>(not drawn: no data)</p>")
    body = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title><style>{_STYLE}</style></head><body>
<h1>{esc(title)}</h1>
<h2>The file</h2>
{_table(facts)}
<details><summary>waveforest info</summary><pre>{esc(summary_text)}</pre></details>
<h2>CFD against the sensor's DR echoes</h2>
<p class="{'ok' if passed else 'miss'}">{esc(verdict)}</p>
{_table(agreement_rows)}
<p class="note">{esc(note)}</p>
{img("cfd", "residuals against amplitude and echo width")}
<h2>Waveforms</h2>
<p>Red dashed: the sensor's DR echoes. Green: the tuned CFD's echoes (range-corrected). Grey: the noise mean and
the CFD arming level.</p>
{img("gallery", "waveform gallery")}
<h2>First-echo features</h2>
{img("histograms", "feature histograms")}
<h2>Map</h2>
{img("map", "feature map")}
<h2>Files</h2>
{_table(files)}
</body></html>
"""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(body, encoding="utf-8")
    return path
