"""Run a survey end to end: tiles (resumable, optionally one part of N), then the merge into DIR.

Tile files live in a hidden cache folder beside DIR, ``.DIR.survey-<key>`` (key: a hash of
the scene's triangles and plants, the survey and the settings), so an interrupted run, or N
jobs each running one part, leave only completed tiles there; :func:`merge` writes DIR whole
or not at all (:class:`waveforest.atomic.OutputFolder`) and then removes DIR's caches (this
run's and those of earlier runs with other inputs).

DIR holds ``survey.las`` (or ``survey.laz``) with ``survey.wdp`` (external packets),
``trajectory.csv``, ``summary.json`` and, on request, ``truth.parquet``.
"""

from __future__ import annotations

import json
import resource
import shutil
import time
import warnings
from contextlib import suppress
from pathlib import Path

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.atomic import OutputFolder, atomic_path
from waveforest.errors import WaveforestWarning
from waveforest.io.las.write import GPS_WEEK_S, WaveformLasWriter, creation_today
from waveforest.model.forward import MCRTSetup, SensorSetup
from waveforest.survey.engine import (
    ADAPTIVE_TILE_PULSES,
    Plan,
    TileResult,
    TileScenes,
    max_zenith_tan,
    plan,
    run_key,
    run_tile,
    summary,
    write_summary,
)
from waveforest.survey.scan import trajectory_table
from waveforest.survey.scene import SurveyScene
from waveforest.survey.spec import Survey, SurveyError

LOCAL_WKT = ('LOCAL_CS["waveforest survey frame (local metric)",LOCAL_DATUM["scene",0],'
             'UNIT["metre",1],AXIS["x",EAST],AXIS["y",NORTH]]')
"""CRS written when the survey names none: the scene's local metric frame."""

COMMAND = "survey"

LAZ_CHUNK_POINTS = 1_000_000
"""Points compressed per chunk when the survey writes LAZ."""


def cache_folder(out_dir: Path, key: str) -> Path:
    out_dir = Path(out_dir)
    return out_dir.parent / f".{out_dir.name}.survey-{key}"


def peak_memory_mb() -> float:
    """Peak resident memory of this process, MB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_tiles(scene: SurveyScene, survey: Survey, mcrt: MCRTSetup, setup: SensorSetup,
              out_dir: Path, *, part: tuple[int, int] = (0, 1), threads: int | None = None,
              progress: bool = False) -> tuple[Plan, Path]:
    """Trace every tile of part ``part = (i, n)`` (tiles ``k`` with ``k % n == i``) not yet in the cache
    (under the adaptive ray budget, tiles of :data:`~waveforest.survey.engine.ADAPTIVE_TILE_PULSES`
    pulses on average)."""
    wall = time.perf_counter()
    pl = plan(scene, survey, 1 if mcrt.tolerance is None else ADAPTIVE_TILE_PULSES)
    cache = cache_folder(out_dir, run_key(scene, survey, mcrt, repr(setup)))
    cache.mkdir(parents=True, exist_ok=True)
    todo = [k for k in range(len(pl.tiles)) if k % part[1] == part[0]]
    counts = np.bincount(np.searchsorted(pl.tiles, pl.tile), minlength=len(pl.tiles))
    missing = [k for k in todo if not tile_complete(cache, k, survey.truth)]
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=int(counts[todo].sum()), initial=int(counts[todo].sum() - counts[missing].sum()),
                   unit="pulse", desc="survey", smoothing=0.1)
    cpu = time.process_time()
    scenes = TileScenes(scene, survey, mcrt.viewed_diameter_m, max_zenith_tan(pl.pulses)) if missing else None
    prepare_s = time.process_time() - cpu
    traced = 0
    try:
        for k in missing:
            res = run_tile(k, pl, scenes, survey, mcrt, setup, cache / f"tile_{k:06d}.parquet", threads, bar)
            with atomic_path(cache / f"tile_{k:06d}.json") as tmp:  # written last: the tile is complete
                tmp.write_text(json.dumps(res.__dict__))
            traced += 1
    except BaseException:  # interrupted or failed: say what a rerun of the same command resumes from
        done = len(todo) - len(missing) + traced
        if done:
            warnings.warn(f"{done} of {len(todo)} tiles complete in {cache}: the same command resumes from them",
                          WaveforestWarning, stacklevel=2)
        raise
    finally:
        if bar is not None:
            bar.close()
        if traced:  # this run's prototypes and BVHs (a resumed run builds them anew), wall time and
            # memory, also when it was interrupted: the summary counts every run that traced
            runs = len(list(cache.glob(f"run_{part[0]}_{part[1]}_*.json")))
            with suppress(OSError), atomic_path(cache / f"run_{part[0]}_{part[1]}_{runs}.json") as tmp:
                tmp.write_text(json.dumps({"prototype_build_s": scene.build_s + prepare_s,
                                           "wall_s": time.perf_counter() - wall, "peak_memory_mb": peak_memory_mb()}))
    return pl, cache


def tile_complete(cache: Path, k: int, truth: bool) -> bool:
    """Tile ``k`` is in ``cache``: its record (written last) and readable Parquet files, the pulse
    table with the record's recorded pulses (a file damaged after its run is traced again)."""
    record = cache / f"tile_{k:06d}.json"
    if not record.exists():
        return False
    try:
        recorded = json.loads(record.read_text())["recorded"]
        files = [cache / f"tile_{k:06d}.parquet"] + ([cache / f"tile_{k:06d}.truth.parquet"] if truth else [])
        rows = [pq.read_metadata(f).num_rows for f in files]
    except (OSError, ValueError, KeyError, pa.ArrowException):
        return False
    return rows[0] == recorded


def in_time_order(tiles: list[Path], window: int):
    """The pulse tables of ``tiles`` as tables of about ``window`` pulses in GPS-time order, as a
    sensor records them. A window reads the tiles that hold some of its pulses and keeps them
    for the next (a tile is read about once per pass of the flight over it), so memory is that
    of the tiles one window touches, not of the survey."""
    times = [pq.read_table(f, columns=["gps_time"]).column(0).to_numpy() for f in tiles]
    order = [np.argsort(t, kind="stable") for t in times]
    times = [t[o] for t, o in zip(times, order)]
    every = np.sort(np.concatenate(times)) if times else np.zeros(0)
    edges = np.append(every[::window], np.inf)
    loaded: dict[int, pa.Table] = {}
    for lo, hi in zip(edges[:-1], edges[1:]):
        parts, touched = [], {}
        for k, t in enumerate(times):
            a, b = np.searchsorted(t, [lo, hi])
            if b > a:
                touched[k] = loaded[k] if k in loaded else pq.read_table(tiles[k])
                parts.append(touched[k].take(order[k][a:b]))
        loaded = touched
        table = pa.concat_tables(parts)
        yield table.take(np.argsort(table.column("gps_time").to_numpy(), kind="stable"))


def merge(pl: Plan, cache: Path, scene: SurveyScene, survey: Survey, out_dir: Path, *, force: bool = False,
          mcrt: MCRTSetup, inputs=()) -> dict:
    """Write DIR from the cached tiles (all must be there); return the summary: wall time the
    sum of the runs that traced tiles (parts, resumed runs) and of this merge, peak memory the
    largest of theirs."""
    t0 = time.perf_counter()
    folder = OutputFolder(out_dir, COMMAND, force=force, inputs=inputs)
    missing = [k for k in range(len(pl.tiles)) if not tile_complete(cache, k, survey.truth)]
    if missing:
        raise SurveyError(f"{cache}: tiles {missing[0]} and {len(missing) - 1} more not traced yet "
                          "(run every part first)")
    results = [TileResult(**json.loads((cache / f"tile_{k:06d}.json").read_text())) for k in range(len(pl.tiles))]
    with folder as tmp:
        las = tmp / "survey.las"
        last = max(float(tr.gps_time[-1]) for tr in pl.tracks)
        with WaveformLasWriter(las, version=survey.las_version, bits=survey.scanner.bits,
                               storage=survey.waveforms, agc_attribute="user_data", wkt=survey.crs_wkt or LOCAL_WKT,
                               generating_software="waveforest survey", creation=creation_today(),
                               gps_time_type="week" if last < GPS_WEEK_S else "standard") as w:
            for t in in_time_order([cache / f"tile_{k:06d}.parquet" for k in range(len(pl.tiles))],
                                   survey.chunk_pulses):
                w.write(t)
            if w.n_pulses == 0:
                raise SurveyError(f"{survey.source}: no pulse returned an echo (expected a scene the beams reach)")
        if survey.laz:  # points compressed chunk by chunk; header, VLRs and EVLRs as written
            with laspy.open(las) as reader, laspy.open(tmp / "survey.laz", mode="w", header=reader.header,
                                                       do_compress=True, laz_backend=laspy.LazBackend.Lazrs) as out:
                for points in reader.chunk_iterator(LAZ_CHUNK_POINTS):
                    out.write_points(points)
            las.unlink()
        trajectory_table(pl.tracks, survey.trajectory_hz).to_csv(tmp / "trajectory.csv", index=False,
                                                                 float_format="%.6f")
        if survey.truth:  # in GPS-time order, as the LAS points
            truths = [f for f in (cache / f"tile_{k:06d}.truth.parquet" for k in range(len(pl.tiles)))
                      if pq.read_metadata(f).num_rows]
            writer = None
            try:
                for t in in_time_order(truths, survey.chunk_pulses):
                    writer = writer or pq.ParquetWriter(tmp / "truth.parquet", t.schema)
                    writer.write_table(t)
            finally:
                if writer is not None:
                    writer.close()
        runs = [json.loads(f.read_text()) for f in sorted(cache.glob("run_*.json"))]
        out = summary(pl, results, sum(r["wall_s"] for r in runs) + time.perf_counter() - t0,
                      max([peak_memory_mb()] + [r["peak_memory_mb"] for r in runs]), mcrt)
        out["prototypes"] = 0 if scene.plants is None else len(scene.plants.prototypes)
        out["prototype_build_s"] = float(sum(r["prototype_build_s"] for r in runs))
        write_summary(out, tmp / "summary.json")
    for old in Path(out_dir).parent.glob(f".{Path(out_dir).name}.survey-*"):  # this run's and stale ones
        shutil.rmtree(old, ignore_errors=True)
    return out


def run_survey(scene: SurveyScene, survey: Survey, mcrt: MCRTSetup, setup: SensorSetup,
               out_dir: Path, *, force: bool = False, threads: int | None = None, progress: bool = False,
               part: tuple[int, int] | None = None, inputs=()) -> dict | None:
    """Trace (resuming) and merge; with ``part`` only that part's tiles are traced (no merge, None).
    ``inputs``: the files the survey reads (an output folder holding one is refused)."""
    OutputFolder(out_dir, COMMAND, force=force, inputs=inputs)  # refuse a foreign folder before any work
    try:
        pl, cache = run_tiles(scene, survey, mcrt, setup, out_dir, part=part or (0, 1),
                              threads=threads, progress=progress)
    except OSError as exc:  # e.g. a full disk: the completed tiles stay for the next run
        raise SurveyError(f"{exc.filename or out_dir}: cannot write a tile ({exc.strerror or exc}); "
                          "the tiles completed so far are kept for a rerun") from None
    if part is not None:
        return None
    try:
        return merge(pl, cache, scene, survey, out_dir, force=force, mcrt=mcrt, inputs=inputs)
    except OSError as exc:
        raise SurveyError(f"{exc.filename or out_dir}: cannot write the survey ({exc.strerror or exc}); "
                          "nothing was written to the output folder") from None
