"""The ``quicklook`` stage: one waveform file (LAS or LAZ) -> pulses, tuned CFD, features and one
HTML page (docs/own-data.md).

Chains :func:`waveforest.stages.ingest.run`, :func:`waveforest.stages.tune_cfd.run` and
:func:`waveforest.stages.features.run_cfd`, then reads the feature table in batches (scalar
columns only) for the histograms, the map and the gallery's choice, and the pulse table once
more for the gallery's waveforms: memory stays within the ingest bound whatever the file size.
"""

from __future__ import annotations

import base64
from pathlib import Path

import click
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.cliutil import EXISTING_FILE, OUT_DIR, stage_options, warnings_to_stderr
from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.las import format_summary, summarise
from waveforest.io.pulses import iter_pulses, list_to_padded
from waveforest.report.quicklook import (
    figure_uri,
    gallery_figure,
    histogram_figure,
    map_figure,
    write_page,
)
from waveforest.sensor.params import CFD_CHECK_M
from waveforest.sensor.self_calibration import BIAS_LIMIT_M, PAPER_SHARE
from waveforest.stages import features as features_stage
from waveforest.stages import ingest as ingest_stage
from waveforest.stages import tune_cfd as tune_stage

HIST_FEATURES = ("Apeak", "FWHM", "E", "Npeaks", "echo_z")
"""First-echo features shown as histograms."""
HIST_BINS = 60
RESERVOIR = 100_000
"""Values per feature kept (seeded) to place the histogram edges."""
_READ = 8192
"""Rows per batch read (waveforms: ~100 MB per batch of 256-sample pulses)."""


def _say(msg: str) -> None:
    click.echo(f"quicklook: {msg}", err=True)


def _scan_features(path: Path, seed: int, map_feature: str):
    """Pass 1 over the feature table: a seeded sample of each feature, the extent, pass/fail per row."""
    n_total = pq.read_metadata(path).num_rows
    rng = np.random.default_rng([int(seed), 0x91C])
    p = min(1.0, RESERVOIR / max(n_total, 1))
    cols = ["echo_time_ns", "cfd_time_ns", "echo_x", "echo_y", *HIST_FEATURES]
    sample = {k: [] for k in HIST_FEATURES}
    ext = np.array([np.inf, -np.inf, np.inf, -np.inf])
    ok, checked = [], []
    for rb in iter_pulses(path, _READ, columns=cols):
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


def _first_of_list(col) -> np.ndarray:
    vals, lens = list_to_padded(col, dtype=np.float64)
    out = np.full(len(lens), np.nan)
    if vals.shape[1]:
        out[lens > 0] = vals[lens > 0, 0]
    return out


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
    size = max(x1 - x0, y1 - y0, 1e-6) / cells
    nx, ny = max(1, int(np.ceil((x1 - x0) / size)) or 1), max(1, int(np.ceil((y1 - y0) / size)) or 1)
    s, c = np.zeros(nx * ny), np.zeros(nx * ny)
    cols = list(dict.fromkeys(["echo_x", "echo_y", map_feature, *edges]))
    for rb in iter_pulses(path, _READ, columns=cols):
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


def _gallery(pulses: Path, features: Path, ok, checked, k: int, seed: int) -> list[dict]:
    """``k`` pulses drawn at random (seeded): half among those that miss 0.10 m (if any), the rest among the others."""
    if k == 0:
        return []
    rng = np.random.default_rng([int(seed), 0x6A1])
    miss = np.flatnonzero(checked & ~ok)
    rest = np.flatnonzero(~(checked & ~ok))
    a = rng.choice(miss, size=min(len(miss), k // 2), replace=False) if len(miss) else np.zeros(0, np.int64)
    b = rng.choice(rest, size=min(len(rest), k - len(a)), replace=False) if len(rest) else np.zeros(0, np.int64)
    rows = np.sort(np.concatenate([a, b]).astype(np.int64))
    want = set(rows.tolist())
    out: dict[int, dict] = {}
    start = 0
    for rb in iter_pulses(features, _READ, columns=["pulse_id", "cfd_time_ns"]):
        idx = rows[(rows >= start) & (rows < start + rb.num_rows)] - start
        if idx.size:
            cfd, lens = list_to_padded(rb.column("cfd_time_ns").take(idx), dtype=np.float64)
            pid = rb.column("pulse_id").to_numpy()[idx]
            for j, r in enumerate(idx):
                out[start + int(r)] = {"cfd_ns": cfd[j, :lens[j]].tolist(), "pulse_id": int(pid[j])}
        start += rb.num_rows
    start = 0
    for batch in iter_pulses(pulses, _READ, columns=["samples", "sampling_ns", "echo_time_ns"]):
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


def run(las_path, out_dir, cfg: dict, *, dataset: str | None = None, trajectory=None, progress: bool = True) -> dict:
    """Ingest, tune the CFD, compute the features and write ``quicklook.html`` into ``out_dir``.

    Returns a dict: the paths written, the tune-cfd result and the feature counts.
    """
    las_path, out = Path(las_path), Path(out_dir)
    if out.exists() and not out.is_dir():
        raise WaveforestError(f"{out}: exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    name = dataset or las_path.stem
    icfg = cfg["ingest"]
    qcfg = cfg["quicklook"]
    seed = int(cfg["seed"])
    pulses, cfd_json, cfd_png = out / "pulses.parquet", out / "cfd.json", out / "cfd.png"
    feats, page = out / "features.parquet", out / "quicklook.html"

    _say(f"1/4 ingest {las_path} -> {pulses}")
    ing = ingest_stage.run(las_path, pulses, dataset=name, trajectory=trajectory, agc_attribute=cfg["agc"]["attribute"],
                           chunk_points=icfg["chunk_points"], bucket_points=icfg["bucket_points"],
                           batch_pulses=icfg["batch_pulses"], progress=progress)
    _say(ing.summary())
    _say(f"2/4 tune-cfd -> {cfd_json}")
    res = tune_stage.run(pulses, cfd_json, cfg, plot_path=cfd_png, progress=progress)
    _say(tune_stage.summary(res, cfd_json))
    _say(f"3/4 features -> {feats}")
    fr = features_stage.run_cfd([pulses], cfd_json, feats, cfg, progress=progress)
    _say(f"4/4 page -> {page}")
    summary_text = format_summary(summarise(las_path, agc_attribute=cfg["agc"]["attribute"],
                                            chunk_points=icfg["chunk_points"], bucket_points=icfg["bucket_points"]))
    sample, ext, ok, checked = _scan_features(feats, seed, qcfg["map_feature"])
    figures = {"cfd": "data:image/png;base64," + base64.b64encode(cfd_png.read_bytes()).decode("ascii")}
    if np.all(np.isfinite(ext)):
        hists, grid, extent = _histograms_and_map(feats, sample, ext, qcfg["map_feature"], int(qcfg["map_cells"]))
        if hists:
            figures["histograms"] = figure_uri(histogram_figure(hists))
        if np.isfinite(grid).any():
            figures["map"] = figure_uri(map_figure(grid, extent, qcfg["map_feature"]))
    gal = _gallery(pulses, feats, ok, checked, int(qcfg["gallery"]), seed)
    if gal:
        figures["gallery"] = figure_uri(gallery_figure(gal, res["noise_mean"],
                                                       res["noise_mean"] + res["cfd"]["arming_sd"] * res["noise_sd"]))
    las = ing.las
    pct = lambda v: "n/a" if v is None else f"{100 * v:.1f} %"  # noqa: E731
    cm = lambda v: "n/a" if v is None else f"{100 * v:.2f} cm"  # noqa: E731
    passed = (res["within_0_10_m"] is not None and res["within_0_10_m"] >= PAPER_SHARE
              and res["median_residual_m"] is not None and abs(res["median_residual_m"]) < BIAS_LIMIT_M)
    verdict = (f"{pct(res['within_0_10_m'])} of the pulses with a DR echo have their first CFD echo within 0.10 m of it "
               f"(paper: > 95 %, no bias): {'criterion met' if passed else 'criterion not met'}")
    facts = [
        ("file", f"{las_path} ({las.file_size:,} bytes)"),
        ("format", f"LAS {las.version}, point format {las.point_format}{', LAZ-compressed' if las.compressed else ''}, "
                   f"{las.waveform.storage} waveforms"),
        ("points / pulses", f"{ing.n_points:,} / {ing.n_pulses:,}"),
        ("sampling", f"{res['sampling_ns']:g} ns"),
        ("AGC", ing.agc_attribute or "none"),
        ("extent (x, y), m", "n/a" if not np.all(np.isfinite(ext)) else
         f"{ext[0]:.1f} .. {ext[1]:.1f}, {ext[2]:.1f} .. {ext[3]:.1f}"),
        ("noise (last samples)", f"{res['noise_mean']:.2f} ± {res['noise_sd']:.2f} DN"),
        ("system pulse FWHM", f"{res['system_fwhm_ns']:.2f} ns (from {res['n_single_echoes']:,} single echoes)"),
    ]
    lim = res["limits"]
    agreement = [
        ("pulses with a DR echo", f"{res['n_pulses']:,}"),
        ("within 0.10 m (all of them)", pct(res["within_0_10_m"])),
        ("within 0.10 m (|dR| < 1 m, same echo)", f"{pct(res['within_0_10_m_gated'])} of {res['n_gated']:,}"),
        ("median residual", cm(res["median_residual_m"])),
        ("residual robust SD", cm(res["residual_sd_robust_m"])),
        ("CFD", f"fraction {res['fraction']:.2f}, delay {res['delay_ns']:.2f} ns "
                f"({'tuned' if res['cfd_tuning']['tuned'] else 'as configured: ' + res['cfd_tuning']['reason']})"),
        *[(f"missed: {k.replace('_', ' ')}", f"{v['n']:,} ({pct(v['share'])})") for k, v in lim.items()],
    ]
    files = [(p.name, what) for p, what in (
        (pulses, "pulse table (waveforest ingest)"), (cfd_json, "noise, CFD and the check (waveforest tune-cfd)"),
        (cfd_png, "residual plot"), (feats, "first-echo features and every CFD echo (waveforest features --cfd)"))]
    write_page(page, title=f"waveforest quicklook: {las_path.name}", summary_text=summary_text, facts=facts,
               agreement_rows=agreement, verdict=verdict, passed=passed, note=res["note"], figures=figures, files=files)
    return {"page": page, "pulses": pulses, "cfd": cfd_json, "features": feats, "tune": res, "n_features": fr.n_pulses,
            "passed": passed}


@click.command()
@click.argument("las_file", type=EXISTING_FILE)
@click.option("--out", "out", type=OUT_DIR, required=True, help="Output folder (pulses, cfd.json, features, quicklook.html).")
@click.option("--dataset", default=None, help="Dataset name (default: the file stem).")
@click.option("--trajectory", type=EXISTING_FILE, default=None,
              help="Optional trajectory CSV (gps_time,x,y,z) for sensor positions and ranges.")
@click.option("--progress/--no-progress", default=True, help="Progress bars on stderr.")
@stage_options
def quicklook(las_file, out, dataset, trajectory, progress, cfg):
    """One look at your own waveform file: ingest, a CFD tuned on the file's own DR echoes,
    first-echo features, and one HTML page (docs/own-data.md).

    LAS_FILE is a LAS or LAZ 1.3/1.4 waveform file (packets in a .wdp beside it or inside).
    """
    with warnings_to_stderr():
        res = run(las_file, out, cfg, dataset=dataset, trajectory=trajectory, progress=progress)
    t = res["tune"]
    click.echo(f"quicklook: {t['dataset']}: {100 * (t['within_0_10_m'] or 0):.1f} % of {t['n_pulses']:,} pulses within "
               f"0.10 m of their DR echo ({'criterion met' if res['passed'] else 'criterion not met'}); wrote {res['page']}")
