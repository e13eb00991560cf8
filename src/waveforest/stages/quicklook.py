"""The ``quicklook`` stage: one waveform file (LAS or LAZ) -> pulses, tuned CFD, features and one
HTML page (docs/own-data.md).

Composes the library as the ``ingest``, ``tune-cfd`` and ``features --cfd`` stages do
(:func:`waveforest.io.las.pulses.las_to_pulses`, :func:`waveforest.model.self_tuning.tune_pulse_table`,
:func:`waveforest.model.features.cfd_features`), then writes the page
(:func:`waveforest.report.quicklook.quicklook_page`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
from dataclasses import replace
from pathlib import Path

import click
import pyarrow as pa

from waveforest import settings
from waveforest.atomic import OutputFolder, write_json
from waveforest.cliutil import EXISTING_FILE, OUT_DIR, force_option, stage_options, warnings_to_stderr
from waveforest.io.las import find_wdp, summarise
from waveforest.io.las.pulses import las_to_pulses
from waveforest.model.features import cfd_features
from waveforest.model.self_tuning import summary_line, tune_pulse_table
from waveforest.report.quicklook import plot_self_tuning, quicklook_page


def _say(msg: str) -> None:
    click.echo(f"quicklook: {msg}", err=True)


def _release_memory() -> None:
    """Hand memory freed by the step before back to the system (Arrow's pool, the C heap), so
    that the steps' peaks do not stack up in one process."""
    gc.collect()
    pa.default_memory_pool().release_unused()
    libc = ctypes.util.find_library("c")
    if libc:
        trim = getattr(ctypes.CDLL(libc), "malloc_trim", None)
        if trim is not None:
            trim(0)


def run(las_path, out_dir, cfg: dict, *, dataset: str | None = None, trajectory=None, progress: bool = True,
        force: bool = False) -> dict:
    """Ingest, tune the CFD, compute the features and write ``quicklook.html`` into ``out_dir``,
    whole or not at all (:class:`waveforest.atomic.OutputFolder`; ``force``: replace a folder
    holding files quicklook did not write).

    Returns a dict: the paths written, the tune-cfd result and the feature counts.
    """
    las_path = Path(las_path)
    inputs = [p for p in (las_path, find_wdp(las_path), trajectory) if p is not None]
    folder = OutputFolder(out_dir, "quicklook", force=force, inputs=inputs)
    with folder:
        return _write(las_path, folder, cfg, dataset=dataset, trajectory=trajectory, progress=progress)


def _write(las_path: Path, folder: OutputFolder, cfg: dict, *, dataset, trajectory, progress: bool) -> dict:
    """:func:`run`'s steps, written into ``folder.tmp``; messages and results name the final paths."""
    out, final = folder.tmp, folder.final
    name = dataset or las_path.stem
    icfg = cfg["ingest"]
    pulses, cfd_json, cfd_png = out / "pulses.parquet", out / "cfd.json", out / "cfd.png"
    feats, page = out / "features.parquet", out / "quicklook.html"

    look = settings.quicklook_settings(cfg)
    # the file's summary first, while the process is small: its reading is the page's peak
    summary = summarise(las_path, agc_attribute=cfg["agc"]["attribute"], chunk_points=icfg["chunk_points"],
                        bucket_points=icfg["bucket_points"], grid_cells=look.map_cells)
    _release_memory()
    _say(f"1/4 ingest {las_path} -> {final(pulses)}")
    ing = las_to_pulses(las_path, pulses, dataset=name, trajectory=trajectory, agc_attribute=cfg["agc"]["attribute"],
                        chunk_points=icfg["chunk_points"], bucket_points=icfg["bucket_points"],
                        batch_pulses=icfg["batch_pulses"], progress=progress)
    ing = replace(ing, out=final(pulses))
    _say(ing.summary())
    _release_memory()
    _say(f"2/4 tune-cfd -> {final(cfd_json)}")
    tuned = tune_pulse_table(pulses, settings.self_tuning_settings(cfg), progress=progress)
    tuned.result["source"] = str(final(pulses))
    write_json(tuned.result, cfd_json)
    plot_self_tuning(tuned, cfd_png, seed=int(cfg["seed"]))
    res = tuned.result
    del tuned  # its per-pulse arrays are not needed further on
    _release_memory()
    _say(summary_line(res, final(cfd_json)))
    _say(f"3/4 features -> {final(feats)}")
    fr = cfd_features([pulses], cfd_json, feats, settings.feature_table_settings(cfg), progress=progress)
    _release_memory()
    _say(f"4/4 page -> {final(page)}")
    passed = quicklook_page(page, las_path=las_path, summary=summary, tuning=res, pulses=pulses, cfd_json=cfd_json,
                            cfd_png=cfd_png, features=feats, settings=look)
    return {"page": final(page), "pulses": final(pulses), "cfd": final(cfd_json), "features": final(feats), "tune": res,
            "n_features": fr.n_pulses, "passed": passed}


@click.command()
@click.argument("las_file", type=EXISTING_FILE)
@click.option("--out", "out", type=OUT_DIR, required=True, help="Output folder (pulses, cfd.json, features, quicklook.html).")
@click.option("--dataset", default=None, help="Dataset name (default: the file stem).")
@click.option("--trajectory", type=EXISTING_FILE, default=None,
              help="Optional trajectory CSV (gps_time,x,y,z) for sensor positions and ranges.")
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
@force_option
@stage_options
def quicklook(las_file, out, dataset, trajectory, progress, force, cfg):
    """One look at your own waveform file: ingest, a CFD tuned on the file's own DR echoes,
    first-echo features, and one HTML page (docs/own-data.md).

    LAS_FILE is a LAS or LAZ 1.3/1.4 waveform file (packets in a .wdp beside it or inside).

    Example:

    \b
    waveforest quicklook flight.laz --out look/
    """
    with warnings_to_stderr():
        res = run(las_file, out, cfg, dataset=dataset, trajectory=trajectory, progress=progress, force=force)
    t = res["tune"]
    click.echo(f"quicklook: {t['dataset']}: {100 * (t['within_0_10_m'] or 0):.1f} % of {t['n_pulses']:,} pulses within "
               f"0.10 m of their DR echo ({'criterion met' if res['passed'] else 'criterion not met'}); wrote {res['page']}")
