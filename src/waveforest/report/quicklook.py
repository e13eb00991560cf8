"""Figures and the HTML page of ``waveforest quicklook`` and the plot of ``tune-cfd``.

The page is one self-contained HTML file: figures are embedded as PNG data URIs, so it can be
mailed or opened anywhere. :func:`quicklook_page` reads the feature table in batches (scalar
columns only) for the histograms, the map, the afterpulse check and the gallery's choice, and the
pulse table once more for the gallery's waveforms: memory stays within the ingest bound whatever
the file size. The file's header block, z outliers and the elevation and density maps come from
the LAS summary (:func:`waveforest.io.las.info.summarise`).

Every number on the page goes through :func:`fmt`: rounded to the decimals of its unit
(:data:`DECIMALS`), never shown as a negative zero.
"""

from __future__ import annotations

import base64
import html
import io
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path
from waveforest.constants import RANGE_PER_NS
from waveforest.io.las.format import GE_WAVEFORM_EXTERNAL, GE_WAVEFORM_INTERNAL
from waveforest.io.las.info import ASPRS_CLASSES, Z_OUTLIER_MIN_M, LasSummary, format_summary, grid_cell_size
from waveforest.io.pulses import iter_pulses, list_to_padded
from waveforest.model.self_tuning import SelfTuning
from waveforest.plotting import pyplot, save_png
from waveforest.rng import named_generator
from waveforest.sensor.cfd_tuning import WIDTH_EDGES
from waveforest.sensor.decompose import decompose
from waveforest.sensor.params import CFD_CHECK_M, RANGE_GATE_M
from waveforest.sensor.self_calibration import BIAS_LIMIT_M, PAPER_SHARE

PLOT_POINTS = 20_000
"""Most pulses drawn in a scatter plot (a seeded random subset beyond that)."""

DECIMALS = {"m": 1, "cm": 1, "ns": 2, "%": 1, "DN": 2, "deg": 1, "s": 1, "per m²": 1, "m²": 0, "": 0}
"""The page's one rounding rule: decimals shown per unit."""
UNIT_TEXT = {"deg": "°", "": ""}


def fmt(value, unit: str = "", *, grouped: bool = True) -> str:
    """``value`` rounded to the decimals of ``unit`` (:data:`DECIMALS`) with its unit; thousands
    grouped unless ``grouped`` is False (coordinates, times); no negative zero; ``n/a`` for
    None or NaN. ``unit="%"`` takes a share (0..1)."""
    if value is None or not np.isfinite(float(value)):
        return "n/a"
    v = 100.0 * float(value) if unit == "%" else float(value)
    d = DECIMALS[unit]
    v = round(v, d) + 0.0  # + 0.0 turns a rounded -0.0 into 0.0
    text = f"{v:{',' if grouped else ''}.{d}f}"
    u = UNIT_TEXT.get(unit, unit)
    return text + ("" if not u else u if u == "°" else f" {u}")


def _subset(n: int, k: int, seed: int) -> np.ndarray:
    if n <= k:
        return np.arange(n)
    return np.sort(named_generator("quicklook_scatter", int(seed)).choice(n, size=k, replace=False))


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


def plot_self_tuning(tuned: SelfTuning, path, *, seed: int) -> Path:
    """The residual plot of a :class:`~waveforest.model.self_tuning.SelfTuning` as a PNG (atomically)."""
    return plot_cfd_residuals(tuned.amplitude, tuned.width_rel, tuned.residual_m, tuned.plotted, tuned.correction,
                              path, title=tuned.plot_title(), seed=seed)


def gallery_figure(waveforms: Sequence[dict], noise_mean: float, arming_level: float, *, cols: int = 3):
    """Waveforms with their DR echoes (red dashed), CFD echoes (green solid, range-corrected) and,
    when an item has ``gd`` ((k, 3): amplitude DN, centre ns, SD ns), its Gaussian decomposition
    (blue: the fitted sum over the noise mean, and a dot on each echo's peak).

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
        gd = w.get("gd")
        if gd is not None and len(gd):
            tt = np.asarray(w["t_ns"], np.float64)
            fit = noise_mean + sum(a * np.exp(-0.5 * ((tt - mu) / sd) ** 2) for a, mu, sd in gd)
            ax.plot(tt, fit, color="tab:blue", lw=1.0)
            ax.plot([mu for _, mu, _ in gd], [noise_mean + a for a, _, _ in gd], "o", color="tab:blue", ms=3)
        ax.set_title(w["label"], fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("time from the first sample, ns", fontsize=8)
    fig.tight_layout()
    return fig


FEATURE_AXES = {"Apeak": "Apeak, DN above the noise mean", "FWHM": "FWHM, ns", "E": "E, DN (sample sum × 1 ns)",
                 "Npeaks": "Npeaks (peaks in the first echo)", "echo_z": "first-echo z, m"}
"""Axis label (with unit) of each first-echo feature."""
PAGE_PX = 1100
"""Width of the page's figures, pixels (drawn at :data:`FIGURE_DPI`, shown 1:1)."""
FIGURE_DPI = 100
FONT_PT = 11
"""Font size of the page's figures; at 1:1 display 11 pt at 100 dpi shows as 15 px (9 pt at 96 dpi is 12 px)."""


def decomposition_figure(counts: np.ndarray, profile_x: np.ndarray, profile_z: np.ndarray, strip: str):
    """Echoes per pulse (bar chart of ``counts``: pulses with 0, 1, 2, ... echoes) and a profile:
    echo z against x of the sampled pulses in a strip (``strip`` describes it)."""
    plt = pyplot()
    _page_style(plt)
    fig, (a, b) = plt.subplots(1, 2, figsize=(PAGE_PX / FIGURE_DPI, 3.6), dpi=FIGURE_DPI, layout="constrained",
                               gridspec_kw={"width_ratios": [1, 2]})
    a.bar(np.arange(len(counts)), counts, color="tab:blue")
    a.set_xlabel("echoes per pulse")
    a.set_ylabel("pulses (sample)")
    b.plot(profile_x, profile_z, ".", ms=2, color="tab:blue")
    b.ticklabel_format(useOffset=False, style="plain")
    b.set_xlabel("x, m")
    b.set_ylabel("echo z, m")
    b.set_title(strip, fontsize=FONT_PT)
    return fig


def _page_style(plt) -> None:
    plt.rcParams.update({"font.size": FONT_PT, "axes.titlesize": FONT_PT, "axes.labelsize": FONT_PT,
                         "xtick.labelsize": FONT_PT - 1, "ytick.labelsize": FONT_PT - 1, "legend.fontsize": FONT_PT - 1})


def histogram_figure(hists: dict):
    """One panel per feature, three a row: ``hists[name] = (counts, edges, n_nan)``; axis labels
    with units (:data:`FEATURE_AXES`), sized to show 1:1 on the page."""
    plt = pyplot()
    _page_style(plt)
    k = max(len(hists), 1)
    cols = min(k, 3)
    rows = (k + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(PAGE_PX / FIGURE_DPI, 3.3 * rows), squeeze=False)
    for ax in axes.ravel()[len(hists):]:
        ax.set_visible(False)
    for ax, (name, (counts, edges, n_nan)) in zip(axes.ravel(), hists.items()):
        ax.stairs(counts, edges, fill=True, color="tab:blue", alpha=0.7)
        ax.set_xlabel(FEATURE_AXES.get(name, name))
        ax.set_ylabel("pulses")
        ax.set_title(f"{fmt(counts.sum())} pulses" + (f", {fmt(n_nan)} without" if n_nan else ""))
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def _map_panel(fig, ax, grid, extent, label: str, *, cmap: str = "viridis", robust: bool = True):
    """One gridded map on ``ax`` (equal aspect, x right, y up) with a colorbar the map's height (an
    inset in axes coordinates follows the aspect-fitted box)."""
    finite = grid[np.isfinite(grid)]
    lo, hi = (np.percentile(finite, [2, 98]) if robust else (finite.min(), finite.max())) if finite.size else (0, 1)
    im = ax.imshow(grid, origin="lower", extent=extent, vmin=lo, vmax=hi if hi > lo else lo + 1, cmap=cmap,
                   interpolation="nearest")
    ax.set_aspect("equal")
    ax.set_xlabel("x, m")
    ax.set_ylabel("y, m")
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(axis="x", labelrotation=20)
    cax = ax.inset_axes([1.03, 0.0, 0.04, 1.0])
    fig.colorbar(im, cax=cax, label=label)


def _figure_size(extent, panels: int) -> tuple[float, float]:
    x0, x1, y0, y1 = extent
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    w = PAGE_PX / FIGURE_DPI
    return w, float(np.clip(w / panels * 0.8 * aspect + 1.2, 3.0, 9.0))


def map_figure(grid: np.ndarray, extent: tuple[float, float, float, float], name: str):
    """Mean of a first-echo feature per cell over the file's extent (x right, y up; NaN cells blank)."""
    plt = pyplot()
    _page_style(plt)
    fig, ax = plt.subplots(figsize=_figure_size(extent, 2))
    _map_panel(fig, ax, grid, extent, f"mean {FEATURE_AXES.get(name, name)}")
    fig.tight_layout()
    return fig


def elevation_density_figure(summary: LasSummary):
    """Two maps of the LAS summary's grid: the highest point per cell (z outliers left out), m, and
    the points per m² per cell."""
    plt = pyplot()
    _page_style(plt)
    g = summary.grid
    fig, axes = plt.subplots(1, 2, figsize=_figure_size(g.extent, 2))
    _map_panel(fig, axes[0], g.top_z, g.extent, "highest point in the cell, z, m", cmap="terrain")
    density = np.where(g.count > 0, g.count / g.cell_m**2, np.nan)
    _map_panel(fig, axes[1], density, g.extent, "points per m²", cmap="magma", robust=False)
    axes[0].set_title(f"elevation ({fmt(g.cell_m, 'm')} cells)")
    axes[1].set_title(f"point density ({fmt(g.cell_m, 'm')} cells)")
    fig.tight_layout()
    return fig


def figure_uri(fig) -> str:
    """A figure as a PNG data URI (the figure is closed)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=FIGURE_DPI, bbox_inches="tight", pad_inches=0.1)
    pyplot().close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _table(rows: Sequence[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows) + "</table>"


_STYLE = """body{font-family:system-ui,sans-serif;max-width:1150px;margin:2em auto;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:0.9em}th,td{padding:2px 10px;text-align:left;border-bottom:1px solid #eee}
th{font-weight:600}pre{background:#f6f6f6;padding:0.8em;overflow-x:auto;font-size:0.8em}
img{max-width:100%;height:auto}.ok{color:#176317;font-weight:600}.miss{color:#a0241c;font-weight:600}
p.note{background:#f3f6fb;padding:0.6em 0.9em;border-left:4px solid #4a78b5}"""


def write_page(path, *, title: str, summary_text: str, facts: Sequence[tuple[str, str]], agreement_rows,
               verdict: str, passed: bool, notes: Sequence[str], figures: dict[str, str],
               files: Sequence[tuple[str, str]], map_name: str = "") -> Path:
    """Write the quicklook page (atomically).

    ``figures``: section name -> data URI (``maps``, ``cfd``, ``gallery``, ``decomposition``,
    ``histograms``, ``map``).
    ``notes``: paragraphs shown under the file's facts (e.g. an afterpulse).
    ``files``: (name, what) of the outputs beside the page.
    """
    esc = html.escape
    img = lambda key, alt: (f'<img src="{figures[key]}" alt="{esc(alt)}">' if key in figures else  # noqa: E731
                            "<p>(not drawn: no data)</p>")
    note_html = "".join(f'<p class="note">{esc(n)}</p>' for n in notes)
    body = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{esc(title)}</title><style>{_STYLE}</style></head><body>
<h1>{esc(title)}</h1>
<h2>The file</h2>
{_table(facts)}
{note_html}
<details><summary>waveforest info</summary><pre>{esc(summary_text)}</pre></details>
<h2>Elevation and point density</h2>
{img("maps", "elevation and point density maps")}
<h2>CFD against the sensor's DR echoes</h2>
<p class="{'ok' if passed else 'miss'}">{esc(verdict)}</p>
{_table(agreement_rows)}
{img("cfd", "residuals against amplitude and echo width")}
<h2>Waveforms</h2>
<p>Red dashed: the sensor's DR echoes. Green: the tuned CFD's echoes (range-corrected). Blue: the Gaussian
decomposition (the fitted sum and each echo's peak; <code>waveforest decompose</code>). Grey: the noise mean and
the CFD arming level.</p>
{img("gallery", "waveform gallery")}
<h2>Echoes of the Gaussian decomposition</h2>
<p>A seeded sample of at most {DECOMPOSED:,} pulses: how many echoes each holds, and a cross-section of their
echoes by height. <code>waveforest decompose</code> writes every echo of the file as a point cloud.</p>
{img("decomposition", "echoes per pulse and a profile of the echoes")}
<h2>First-echo features</h2>
{img("histograms", "feature histograms")}
<h2>Map of the first echoes' {esc(map_name)}</h2>
{img("map", "feature map")}
<h2>Files</h2>
{_table(files)}
</body></html>
"""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(body, encoding="utf-8")
    return path


# -- the quicklook page from its tables ------------------------------------------------------

HIST_FEATURES = ("Apeak", "FWHM", "E", "Npeaks", "echo_z")
"""First-echo features shown as histograms."""
HIST_BINS = 60
RESERVOIR = 100_000
"""Values per feature kept (seeded) to place the histogram edges."""
READ_ROWS = 8192
"""Rows per batch read (waveforms: ~100 MB per batch of 256-sample pulses)."""


@dataclass(frozen=True)
class QuicklookSettings:
    """The page's settings (config ``quicklook`` and the seed): gallery waveforms, the mapped
    feature (one of :data:`HIST_FEATURES`), map cells along the longer side."""

    seed: int
    gallery: int
    map_feature: str
    map_cells: int


def _first_of_list(col) -> np.ndarray:
    vals, lens = list_to_padded(col, dtype=np.float64)
    out = np.full(len(lens), np.nan)
    if vals.shape[1]:
        out[lens > 0] = vals[lens > 0, 0]
    return out


def _scan_features(path: Path, seed: int):
    """Pass 1 over the feature table: a seeded sample of each feature, the extent, pass/fail per row."""
    n_total = pq.read_metadata(path).num_rows
    rng = named_generator("quicklook_reservoir", int(seed))
    p = min(1.0, RESERVOIR / max(n_total, 1))
    cols = ["echo_time_ns", "cfd_time_ns", "echo_x", "echo_y", *HIST_FEATURES]
    sample = {k: [] for k in HIST_FEATURES}
    ext = np.array([np.inf, -np.inf, np.inf, -np.inf])
    ok, checked = [], []
    for rb in iter_pulses(path, READ_ROWS, columns=cols):
        take = rng.random(rb.num_rows) < p
        for k in HIST_FEATURES:
            v = rb.column(k).to_numpy(zero_copy_only=False).astype(np.float64)
            sample[k].append(v[take])
        x = rb.column("echo_x").to_numpy(zero_copy_only=False)
        y = rb.column("echo_y").to_numpy(zero_copy_only=False)
        fin = np.isfinite(x) & np.isfinite(y)
        if fin.any():
            ext = np.array([min(ext[0], x[fin].min()), max(ext[1], x[fin].max()),
                            min(ext[2], y[fin].min()), max(ext[3], y[fin].max())])
        te = rb.column("echo_time_ns").to_numpy(zero_copy_only=False)
        tc = _first_of_list(rb.column("cfd_time_ns"))
        r = (te - tc) * RANGE_PER_NS
        ok.append(np.abs(r) < CFD_CHECK_M)
        checked.append(np.isfinite(te))
    return ({k: np.concatenate(v) for k, v in sample.items()}, ext, np.concatenate(ok), np.concatenate(checked))


def _histograms_and_map(path: Path, sample: dict, ext, map_feature: str, cells: int):
    """Pass 2: histograms over every row (edges from the sample) and the mean of ``map_feature`` per cell."""
    edges = {}
    for k, v in sample.items():
        v = v[np.isfinite(v)]
        if not v.size:
            continue
        lo, hi = np.percentile(v, [0.5, 99.5])
        if k == "Npeaks":
            edges[k] = np.arange(0.5, max(hi, 1) + 1.5)
        else:
            edges[k] = np.linspace(lo, hi if hi > lo else lo + 1, HIST_BINS + 1)
    counts = {k: np.zeros(len(e) - 1) for k, e in edges.items()}
    nan = {k: 0 for k in edges}
    x0, x1, y0, y1 = ext
    size = max(grid_cell_size(x1 - x0, y1 - y0, pq.read_metadata(path).num_rows, cells), 1e-6)
    nx, ny = max(1, int(np.ceil((x1 - x0) / size)) or 1), max(1, int(np.ceil((y1 - y0) / size)) or 1)
    s, c = np.zeros(nx * ny), np.zeros(nx * ny)
    cols = list(dict.fromkeys(["echo_x", "echo_y", map_feature, *edges]))
    for rb in iter_pulses(path, READ_ROWS, columns=cols):
        for k, e in edges.items():
            v = rb.column(k).to_numpy(zero_copy_only=False).astype(np.float64)
            fin = np.isfinite(v)
            nan[k] += int((~fin).sum())
            counts[k] += np.histogram(np.clip(v[fin], e[0], e[-1]), e)[0]
        x = rb.column("echo_x").to_numpy(zero_copy_only=False)
        y = rb.column("echo_y").to_numpy(zero_copy_only=False)
        f = rb.column(map_feature).to_numpy(zero_copy_only=False).astype(np.float64)
        fin = np.isfinite(x) & np.isfinite(y) & np.isfinite(f)
        ix = np.clip(((x[fin] - x0) / size).astype(np.int64), 0, nx - 1)
        iy = np.clip(((y[fin] - y0) / size).astype(np.int64), 0, ny - 1)
        cell = iy * nx + ix
        s += np.bincount(cell, f[fin], minlength=nx * ny)
        c += np.bincount(cell, minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        grid = np.where(c > 0, s / c, np.nan).reshape(ny, nx)
    hists = {k: (counts[k], edges[k], nan[k]) for k in edges}
    return hists, grid, (x0, x0 + nx * size, y0, y0 + ny * size)


def nth_true(mask: np.ndarray, ranks: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
    """``np.flatnonzero(mask)[ranks]`` without the index array of every true element (8 bytes
    each): ``mask`` is scanned in chunks of ``chunk`` elements."""
    ranks = np.asarray(ranks, np.int64)
    out = np.empty(len(ranks), np.int64)
    before = 0
    for start in range(0, len(mask), chunk):
        part = mask[start:start + chunk]
        n = int(np.count_nonzero(part))
        inside = (ranks >= before) & (ranks < before + n)
        if inside.any():
            out[inside] = start + np.flatnonzero(part)[ranks[inside] - before]
        before += n
    if len(ranks) and (ranks.min() < 0 or ranks.max() >= before):
        raise IndexError(f"rank out of range: {before} true elements")
    return out


def _gallery(pulses: Path, features: Path, ok, checked, k: int, seed: int) -> list[dict]:
    """``k`` pulses drawn at random (seeded): half among those that miss 0.10 m (if any), the rest among the others."""
    if k == 0:
        return []
    rng = named_generator("quicklook_gallery", int(seed))
    miss = checked & ~ok
    n_miss = int(np.count_nonzero(miss))
    n_rest = len(miss) - n_miss
    # ranks among the misses and the rest (the draws of rng.choice on the index arrays themselves)
    a = rng.choice(n_miss, size=min(n_miss, k // 2), replace=False) if n_miss else np.zeros(0, np.int64)
    b = rng.choice(n_rest, size=min(n_rest, k - len(a)), replace=False) if n_rest else np.zeros(0, np.int64)
    rows = np.sort(np.concatenate([nth_true(miss, a), nth_true(~miss, b)]).astype(np.int64))
    want = set(rows.tolist())
    out: dict[int, dict] = {}
    start = 0
    for rb in iter_pulses(features, READ_ROWS, columns=["pulse_id", "cfd_time_ns"]):
        idx = rows[(rows >= start) & (rows < start + rb.num_rows)] - start
        if idx.size:
            cfd, lens = list_to_padded(rb.column("cfd_time_ns").take(idx), dtype=np.float64)
            pid = rb.column("pulse_id").to_numpy()[idx]
            for j, r in enumerate(idx):
                out[start + int(r)] = {"cfd_ns": cfd[j, :lens[j]].tolist(), "pulse_id": int(pid[j])}
        start += rb.num_rows
    start = 0
    for batch in iter_pulses(pulses, READ_ROWS, columns=["samples", "sampling_ns", "echo_time_ns"]):
        idx = rows[(rows >= start) & (rows < start + batch.num_rows)] - start
        if idx.size:
            sub = batch.take(pa.array(idx))
            x, lens = list_to_padded(sub.column("samples"))
            te, tl = list_to_padded(sub.column("echo_time_ns"), dtype=np.float64)
            dt = sub.column("sampling_ns").to_numpy()
            for j, r in enumerate(idx):
                g = out[start + int(r)]
                g.update(t_ns=np.arange(lens[j]) * dt[j], samples=x[j, :lens[j]], dr_ns=te[j, :tl[j]].tolist(),
                         label=f"pulse {g['pulse_id']}" + ("" if bool(ok[start + r]) or not checked[start + r]
                                                           else " (misses 0.10 m)"))
        start += batch.num_rows
    assert want == set(out)
    return [out[r] for r in rows]


DECOMPOSED = 20_000
"""Pulses decomposed (a seeded sample) for the echoes-per-pulse chart and the profile."""


def decomposition_sample(pulses: Path, res: dict, seed: int):
    """Echoes per pulse (counts of 0, 1, 2, ...) and echo (x, y, z) of a seeded sample of at most
    :data:`DECOMPOSED` pulses, decomposed with the tuned noise and system width (docs/method.md §(f2))."""
    n_total = pq.read_metadata(pulses).num_rows
    rng = named_generator("quicklook_decomposition", int(seed))
    p = min(1.0, DECOMPOSED / max(n_total, 1))
    counts = np.zeros(16, np.int64)
    xyz = []
    cols = ["samples", "sampling_ns", *(f"{k}_{a}" for k in ("anchor", "dir") for a in "xyz")]
    for rb in iter_pulses(pulses, READ_ROWS, columns=cols):
        take = np.flatnonzero(rng.random(rb.num_rows) < p)
        if not take.size:
            continue
        sub = rb.take(pa.array(take))
        x, lens = list_to_padded(sub.column("samples"))
        d = decompose(x, lens, sub.column("sampling_ns").to_numpy(zero_copy_only=False), res["noise_mean"],
                      res["noise_sd"], pulse_fwhm_ns=res.get("system_fwhm_ns"), max_echoes=15)
        counts += np.bincount(d.n_echoes.astype(np.int64), minlength=16)[:16]
        has = np.isfinite(d.time_ns)
        rows = np.nonzero(has)[0]
        dist = d.time_ns[has] * RANGE_PER_NS
        xyz.append(np.stack([sub.column(f"anchor_{a}").to_numpy(zero_copy_only=False)[rows]
                             + sub.column(f"dir_{a}").to_numpy(zero_copy_only=False)[rows] * dist for a in "xyz"], 1))
    last = int(np.flatnonzero(counts).max()) + 1 if counts.any() else 1
    return counts[:last], (np.concatenate(xyz) if xyz else np.zeros((0, 3)))


def _profile(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Echoes in a strip along x through the median y: 2 % of the y extent wide, at least 1 m."""
    fin = np.all(np.isfinite(xyz), axis=1)
    xyz = xyz[fin]
    if not len(xyz):
        return np.zeros(0), np.zeros(0), "no echo"
    y0 = float(np.median(xyz[:, 1]))
    half = max(0.5, 0.01 * float(np.ptp(xyz[:, 1])))
    inside = np.abs(xyz[:, 1] - y0) <= half
    return xyz[inside, 0], xyz[inside, 2], f"profile: echoes within {fmt(half, 'm')} of y = {fmt(y0, 'm')}"


def criterion_met(res: dict) -> bool:
    """The paper's criterion on a tune-cfd result: > 95 % within 0.10 m and no bias."""
    return (res["within_0_10_m"] is not None and res["within_0_10_m"] >= PAPER_SHARE
            and res["median_residual_m"] is not None and abs(res["median_residual_m"]) < BIAS_LIMIT_M)


AFTERPULSE_BIN_NS = 0.05
"""Bin of the delay histogram of :func:`detect_afterpulse`, ns."""
AFTERPULSE_MAX_NS = 200.0
AFTERPULSE_WINDOW_NS = 1.5
"""Delays within this of the modal delay count as the afterpulse, ns."""
AFTERPULSE_SHARE = 0.2
"""Least share of single-target pulses with a second CFD echo in the window to call it an afterpulse."""
AFTERPULSE_MAX_SD_NS = 1.0
"""Most robust SD of the delays in the window (a second target's delay varies far more), ns."""


@dataclass(frozen=True)
class Afterpulse:
    """A second echo at a nearly constant delay after the main echo of single-target pulses."""

    delay_ns: float
    """Median delay of the second CFD echo after the first."""
    sd_ns: float
    """Robust SD (1.4826 MAD, from the histogram) of those delays."""
    n: int
    """Single-target pulses with the afterpulse."""
    n_single: int
    """Pulses with exactly one DR echo (single-target)."""

    @property
    def share(self) -> float:
        return self.n / self.n_single

    def note(self) -> str:
        """The page's paragraph on the afterpulse."""
        return (f"The file shows an afterpulse: in {fmt(self.n)} of its {fmt(self.n_single)} single-target pulses "
                f"(one DR echo; {fmt(self.share, '%')}) the CFD finds a second echo {fmt(self.delay_ns, 'ns')} after "
                f"the main one ({fmt(self.delay_ns * RANGE_PER_NS, 'm')} of range), at a nearly constant delay "
                f"(robust SD {fmt(self.sd_ns, 'ns')}): a ringing of the receiver, not a second target. It adds CFD "
                "echoes (and can add a peak, Npeaks) to these pulses in the gallery and the feature table; the first "
                "echo, which the check and the features use, is not affected (docs/own-data.md).")


def _weighted_median(values: np.ndarray, counts: np.ndarray) -> float:
    order = np.argsort(values, kind="stable")
    c = np.cumsum(counts[order])
    return float(values[order][np.searchsorted(c, 0.5 * c[-1])])


def detect_afterpulse(features, system_fwhm_ns: float) -> Afterpulse | None:
    """An afterpulse in a CFD feature table (:func:`waveforest.model.features.cfd_features`), or None.

    Over the pulses with one DR echo (``n_echoes`` = 1), the delays of the second CFD echo after the
    first (longer than ``system_fwhm_ns``, at most :data:`AFTERPULSE_MAX_NS`) are binned in
    :data:`AFTERPULSE_BIN_NS` bins; the delays within :data:`AFTERPULSE_WINDOW_NS` of the modal
    0.5-ns bin are the afterpulse when they are at least :data:`AFTERPULSE_SHARE` of those pulses
    (and at least 20) with a robust SD within :data:`AFTERPULSE_MAX_SD_NS`. One streaming pass.
    """
    edges = np.arange(0.0, AFTERPULSE_MAX_NS + AFTERPULSE_BIN_NS / 2, AFTERPULSE_BIN_NS)
    counts = np.zeros(len(edges) - 1)
    n_single = 0
    for rb in iter_pulses(Path(features), READ_ROWS, columns=["n_echoes", "cfd_time_ns"]):
        single = rb.column("n_echoes").to_numpy(zero_copy_only=False) == 1
        n_single += int(single.sum())
        t, lens = list_to_padded(rb.column("cfd_time_ns"), dtype=np.float64)
        two = single & (lens >= 2)
        if two.any():
            d = t[two, 1] - t[two, 0]
            d = d[np.isfinite(d) & (d > system_fwhm_ns)]
            counts += np.histogram(d, edges)[0]
    if counts.sum() < 20:
        return None
    centres = 0.5 * (edges[1:] + edges[:-1])
    per = int(round(0.5 / AFTERPULSE_BIN_NS))
    coarse = np.add.reduceat(counts, np.arange(0, len(counts), per))
    mode = (np.argmax(coarse) + 0.5) * per * AFTERPULSE_BIN_NS
    inside = np.abs(centres - mode) <= AFTERPULSE_WINDOW_NS
    delay = _weighted_median(centres[inside], counts[inside])
    inside = np.abs(centres - delay) <= AFTERPULSE_WINDOW_NS
    n = int(counts[inside].sum())
    delay = _weighted_median(centres[inside], counts[inside])
    sd = 1.4826 * _weighted_median(np.abs(centres[inside] - delay), counts[inside]) if n else np.inf
    if n < 20 or n < AFTERPULSE_SHARE * n_single or sd > AFTERPULSE_MAX_SD_NS:
        return None
    return Afterpulse(delay_ns=delay, sd_ns=sd, n=n, n_single=n_single)


def _counts(counter, name=lambda k: f"{int(k)}") -> str:
    return "; ".join(f"{name(k)}: {fmt(v)}" for k, v in sorted(counter.items()))


def _facts(las_path: Path, summary: LasSummary, res: dict) -> list[tuple[str, str]]:
    """The page's header block of the file: format, CRS, counts, time, extent, z, density, scan angles,
    sampling, noise, the system pulse width."""
    las = summary.las
    g = fmt
    packets = ("internal" if las.global_encoding & GE_WAVEFORM_INTERNAL else
               "external" if las.global_encoding & GE_WAVEFORM_EXTERNAL else f"{las.waveform.storage} (no flag)")
    where = f" ({las.waveform.path.name})" if las.waveform.storage == "external" else ""
    rows = [
        ("file", f"{las_path} ({g(las.file_size)} bytes)"),
        ("format", f"LAS {las.version}, point format {las.point_format}{', LAZ-compressed' if las.compressed else ''}; "
                   f"waveform packets {packets}{where}"),
        ("coordinate system", summary.crs),
        ("points / pulses", f"{g(summary.n_points)} points in {g(summary.n_pulses)} pulses"),
    ]
    if not summary.n_points:
        return rows
    z0, z1 = summary.mins[2], summary.maxs[2]
    lo, hi = summary.z_window
    gps0, gps1 = summary.gps_range
    scan0, scan1 = summary.scan_range
    rows += [
        ("returns per pulse", _counts(summary.points_per_pulse, lambda k: f"{int(k)} return{'s' if k > 1 else ''}")),
        ("classification", _counts(summary.classes, lambda k: f"{ASPRS_CLASSES.get(int(k), 'user-defined')} ({int(k)})")),
        ("GPS time", f"{g(gps0, 's', grouped=False)} .. {g(gps1, 's', grouped=False)} (span {g(gps1 - gps0, 's')})"),
        ("extent (x, y)", f"{g(summary.mins[0], 'm', grouped=False)} .. {g(summary.maxs[0], 'm', grouped=False)}, "
                          f"{g(summary.mins[1], 'm', grouped=False)} .. {g(summary.maxs[1], 'm', grouped=False)} "
                          f"({g(summary.maxs[0] - summary.mins[0], 'm')} × {g(summary.maxs[1] - summary.mins[1], 'm')})"),
        ("z range", f"{g(z0, 'm', grouped=False)} .. {g(z1, 'm', grouped=False)}; {g(summary.n_z_outliers)} "
                    f"outlier{'' if summary.n_z_outliers == 1 else 's'} outside {g(lo, 'm', grouped=False)} .. "
                    f"{g(hi, 'm', grouped=False)} (rule: below P1 − d or above P99 + d, P1 and P99 the 1st and 99th "
                    f"percentiles of z, d = max(P99 − P1, {g(Z_OUTLIER_MIN_M, 'm')}))"),
        ("point density", f"points {g(summary.density, 'per m²')}, pulses {g(summary.n_pulses / summary.grid.covered_m2, 'per m²')}, "
                          f"over the {g(summary.grid.covered_m2, 'm²')} covered ({g(summary.grid.cell_m, 'm')} cells "
                          "holding a point)"),
        ("scan angle", "n/a" if not np.isfinite(scan0) else f"{g(scan0, 'deg')} .. {g(scan1, 'deg')}"),
        ("sampling", g(res["sampling_ns"], "ns")),
        ("AGC", summary.agc_dimension or "none"),
        ("noise (last samples)", f"{g(res['noise_mean'], 'DN')} ± {g(res['noise_sd'], 'DN')} (mean ± SD)"),
        ("system pulse FWHM", f"{g(res['system_fwhm_ns'], 'ns')} (tuned CFD, from {g(res['n_single_echoes'])} single echoes)"),
    ]
    return rows


LIMIT_LABELS = {
    "no_cfd_echo": "no CFD echo at all",
    "dr_below_noise": "DR echo not above the waveform noise",
    "other_echo": "CFD on another return (|dR| ≥ 1 m)",
    "same_echo_off": "same echo, 0.10–1 m off",
}
"""What each miss of the CFD-DR check means (keys of the tune-cfd result's ``limits``)."""


def _agreement_rows(res: dict) -> list[tuple[str, str]]:
    """The page's table of the CFD-DR check of a tune-cfd result."""
    return [
        ("pulses with a DR echo", fmt(res["n_pulses"])),
        ("within 0.10 m (all of them)", fmt(res["within_0_10_m"], "%")),
        ("within 0.10 m (|dR| < 1 m, same echo)", f"{fmt(res['within_0_10_m_gated'], '%')} of {fmt(res['n_gated'])}"),
        ("median residual", fmt(None if res["median_residual_m"] is None else 100 * res["median_residual_m"], "cm")),
        ("residual robust SD", fmt(None if res["residual_sd_robust_m"] is None else 100 * res["residual_sd_robust_m"], "cm")),
        ("CFD", f"fraction {fmt(res['fraction'], '%')}, delay {fmt(res['delay_ns'], 'ns')} "
                f"({'tuned' if res['cfd_tuning']['tuned'] else 'as configured: ' + res['cfd_tuning']['reason']})"),
        *[(f"missed: {LIMIT_LABELS.get(k, k.replace('_', ' '))}", f"{fmt(v['n'])} ({fmt(v['share'], '%')})")
          for k, v in res["limits"].items()],
    ]


def quicklook_page(page, *, las_path, summary: LasSummary, tuning: dict, pulses, cfd_json, cfd_png, features,
                   settings: QuicklookSettings) -> bool:
    """Write the quicklook page of one file (atomically); True if the paper's criterion is met.

    ``summary``: the LAS summary of ``las_path`` (:func:`waveforest.io.las.info.summarise`);
    ``pulses``: the ingested pulse table; ``tuning``: the tune-cfd result written to ``cfd_json``,
    its plot ``cfd_png``; ``features``: the CFD feature table (:func:`waveforest.model.features.cfd_features`).
    """
    las_path, pulses, features = Path(las_path), Path(pulses), Path(features)
    cfd_json, cfd_png = Path(cfd_json), Path(cfd_png)
    res = tuning
    sample, ext, ok, checked = _scan_features(features, settings.seed)
    figures = {}
    if summary.grid is not None and summary.grid.count.any():
        figures["maps"] = figure_uri(elevation_density_figure(summary))
    figures["cfd"] = "data:image/png;base64," + base64.b64encode(cfd_png.read_bytes()).decode("ascii")
    if np.all(np.isfinite(ext)):
        hists, grid, extent = _histograms_and_map(features, sample, ext, settings.map_feature, settings.map_cells)
        if hists:
            figures["histograms"] = figure_uri(histogram_figure(hists))
        if np.isfinite(grid).any():
            figures["map"] = figure_uri(map_figure(grid, extent, settings.map_feature))
    gal = _gallery(pulses, features, ok, checked, settings.gallery, settings.seed)
    del sample, ok, checked  # 2 bytes per pulse and the feature sample: not needed further on
    for g in gal:
        d = decompose(g["samples"][None, :], None, float(g["t_ns"][1] - g["t_ns"][0]) if len(g["t_ns"]) > 1 else 1.0,
                      res["noise_mean"], res["noise_sd"], pulse_fwhm_ns=res.get("system_fwhm_ns"), max_echoes=15)
        k = int(d.n_echoes[0])
        g["gd"] = list(zip(d.amplitude[0, :k], d.time_ns[0, :k], d.sigma_ns[0, :k]))
    counts, xyz = decomposition_sample(pulses, res, settings.seed)
    if counts.sum():
        figures["decomposition"] = figure_uri(decomposition_figure(counts, *_profile(xyz)))
    if gal:
        figures["gallery"] = figure_uri(gallery_figure(gal, res["noise_mean"],
                                                       res["noise_mean"] + res["cfd"]["arming_sd"] * res["noise_sd"]))
    passed = criterion_met(res)
    med = res["median_residual_m"]
    verdict = (f"{fmt(res['within_0_10_m'], '%')} of the pulses with a DR echo have their first CFD echo within 0.10 m "
               f"of it, median residual {fmt(None if med is None else 100 * med, 'cm')} (paper: > 95 %, no bias, "
               f"i.e. |median| < {fmt(100 * BIAS_LIMIT_M, 'cm')}): {'criterion met' if passed else 'criterion not met'}")
    after = detect_afterpulse(features, res["system_fwhm_ns"]) if res["system_fwhm_ns"] is not None else None
    files = [(p.name, what) for p, what in (
        (pulses, "pulse table (waveforest ingest)"), (cfd_json, "noise, CFD and the check (waveforest tune-cfd)"),
        (cfd_png, "residual plot"), (features, "first-echo features and every CFD echo (waveforest features --cfd)"))]
    write_page(page, title=f"waveforest quicklook: {las_path.name}", summary_text=format_summary(summary),
               facts=_facts(las_path, summary, res), agreement_rows=_agreement_rows(res), verdict=verdict,
               passed=passed, notes=[after.note()] if after else [], figures=figures, files=files,
               map_name=FEATURE_AXES.get(settings.map_feature, settings.map_feature))
    return passed
