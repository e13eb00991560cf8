"""The ``features`` stage.

With calibration JSONs (``--calibration``, the study's path) it writes the first-echo features
of docs/method.md §(h). With the JSON of ``tune-cfd`` (``--cfd``, a user's own file without
targets) it streams the table and adds, per pulse, the first echo's x and y and every echo of
the tuned CFD, range-corrected, as list columns (:func:`run_cfd`).
"""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path
from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_FILE,
    stage_options,
    warnings_to_stderr,
)
from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.io.pulses import check_pulses, iter_pulses, list_to_padded, padded_to_list, write_table
from waveforest.sensor.calibration import Calibration, load_calibration
from waveforest.sensor.cfd import detect_echoes
from waveforest.sensor.features import FEATURE_NAMES, feature_table
from waveforest.sensor.params import CFDParams, FeatureParams


def run(pulse_paths, calibration_paths, out_path, cfg: dict, *, batch_rows: int = 65536,
        progress: bool = True) -> pd.DataFrame:
    """The ``features`` stage: first-echo features of one or more pulse tables -> one Parquet.

    Parameters
    ----------
    pulse_paths : pulse tables (real, AGC-normalised, or simulated chunks) -- read in batches.
    calibration_paths : calibration JSONs (``calibrate`` output) giving each dataset's noise.
    out_path : feature table (Parquet).  cfg : validated config (sections sensor.features, sensor.cfd).

    Returns
    -------
    pandas.DataFrame, the table written.
    """

    from tqdm import tqdm

    noise, corrections, cfd = {}, {}, {}
    use_rc = bool(cfg["sensor"]["cfd"]["range_correction"])
    for p in calibration_paths:
        cal = load_calibration(p)
        noise[cal.dataset] = cal.meta
        cfd[cal.dataset] = cal.cfd or CFDParams.from_config(cfg)
        if use_rc:
            corrections[cal.dataset] = cal.range_correction_or_identity()
    params = FeatureParams.from_config(cfg)
    parts = []
    for path in pulse_paths:
        path = Path(path)
        if not path.exists():
            raise WaveforestError(f"{path}: no such file")
        for batch in tqdm(iter_pulses(path, batch_rows), desc=f"features: {path.name}", unit="batch",
                          disable=not progress):
            batch = check_pulses(batch, path)
            names = set(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str)))
            unknown = sorted(names - set(noise))
            if unknown:
                raise WaveforestError(
                    f"{path}: dataset(s) {', '.join(unknown)} have no calibration JSON among "
                    f"{', '.join(map(str, calibration_paths)) or '(none)'}")
            parts.append(feature_table(batch, noise, params, cfd=cfd, range_corrections=corrections))
    df = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(
        columns=["dataset", "pulse_id", "source", "n_echoes", "echo_time_ns", *FEATURE_NAMES, "H", "echo_z"])
    write_table(pa.Table.from_pandas(df, preserve_index=False), out_path)
    return df


CFD_COLUMNS = ("cfd_time_ns", "cfd_range_m", "cfd_x", "cfd_y", "cfd_z", "cfd_amplitude")
"""List columns of ``run_cfd``: every echo of the tuned CFD (range-corrected time from the first
sample, ns; range from the sensor, m, NaN if the sensor is unknown; position, m; amplitude above
the noise mean, DN)."""


@dataclass(frozen=True)
class CFDFeatures:
    """What :func:`run_cfd` wrote: rows, rows with a first-echo segment, CFD echoes, rows whose
    first echo came from the CFD (no DR echo)."""

    out: Path
    n_pulses: int
    n_with_segment: int
    n_cfd_echoes: int
    n_first_from_cfd: int


def _cfd_columns(batch: pa.Table, cal: Calibration, cfd: CFDParams, max_echoes: int, use_rc: bool) -> dict:
    """The CFD echoes of a batch as Arrow list columns (:data:`CFD_COLUMNS`) and their count."""
    x, lens = list_to_padded(batch.column("samples"))
    dt = batch.column("sampling_ns").to_numpy(zero_copy_only=False).astype(np.float64)
    ech = detect_echoes(x, lens, dt, cal.noise_mean, cal.noise_sd, cfd, max_echoes,
                        range_correction=cal.range_correction_or_identity() if use_rc else None)
    col = lambda c: batch.column(c).to_numpy(zero_copy_only=False).astype(np.float64)[:, None]  # noqa: E731
    d = ech.times_ns * RANGE_PER_NS
    xyz = [col(f"anchor_{a}") + col(f"dir_{a}") * d for a in "xyz"]
    to_sensor = np.sqrt(sum((col(f"anchor_{a}") - col(f"sensor_{a}")) ** 2 for a in "xyz"))
    counts = ech.n_echoes.astype(np.int64)
    f64 = pa.float64()
    return {
        "n_cfd_echoes": pa.array(ech.n_echoes, pa.int16()),
        "cfd_time_ns": padded_to_list(ech.times_ns, counts, f64),
        "cfd_range_m": padded_to_list(to_sensor + d, counts, f64),
        "cfd_x": padded_to_list(xyz[0], counts, f64),
        "cfd_y": padded_to_list(xyz[1], counts, f64),
        "cfd_z": padded_to_list(xyz[2], counts, f64),
        "cfd_amplitude": padded_to_list(ech.amplitudes, counts, f64),
    }


def run_cfd(pulse_paths, cfd_path, out_path, cfg: dict, *, batch_rows: int = 8192, progress: bool = True) -> CFDFeatures:
    """First-echo features and every CFD echo of pulse tables, with the JSON of ``tune-cfd``.

    Streams: one batch of ``batch_rows`` pulses and one Parquet row group at a time, whatever the
    table's size (8192 pulses of 256 samples take ~100 MB while they are processed).
    The first echo is the first DR echo where the pulse has one (§(h)), else the first CFD echo;
    the features columns are those of :func:`waveforest.sensor.features.feature_table`, then
    ``echo_x``, ``echo_y`` (first-echo position, m), ``n_cfd_echoes`` and :data:`CFD_COLUMNS`.

    Parameters
    ----------
    pulse_paths : pulse tables of the dataset the JSON belongs to.  cfd_path : ``tune-cfd`` JSON
    (noise, fwhm_ns, cfd, range_correction).  out_path : Parquet.  cfg : validated config
    (sections sensor.features, sensor.cfd: max_echoes, range_correction).
    """
    from tqdm import tqdm

    cal = load_calibration(cfd_path)
    name = cal.dataset
    cfd = (cal.cfd or CFDParams.from_config(cfg)).resolved(cal.meta.get("fwhm_ns"))
    use_rc = bool(cfg["sensor"]["cfd"]["range_correction"])
    max_echoes = int(cfg["sensor"]["cfd"]["max_echoes"])
    params = FeatureParams.from_config(cfg)
    rc = {name: cal.range_correction_or_identity()} if use_rc else {}
    n = n_seg = n_echo = n_cfd_first = 0
    with atomic_path(out_path) as tmp:
        writer = None
        try:
            for path in map(Path, pulse_paths):
                if not path.exists():
                    raise WaveforestError(f"{path}: no such file")
                total = pq.read_metadata(path).num_rows
                with tqdm(total=total, unit="pulse", unit_scale=True, disable=not progress, file=sys.stderr,
                          desc=f"features {path.name}") as bar:
                    for batch in iter_pulses(path, batch_rows):
                        batch = check_pulses(batch, path)
                        names = set(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str)))
                        if names - {name}:
                            raise WaveforestError(f"{path}: dataset(s) {', '.join(sorted(names - {name}))} are not the "
                                                  f"dataset of {cfd_path} ({name})")
                        with warnings.catch_warnings():  # counted and said once below
                            warnings.simplefilter("ignore", WaveforestWarning)
                            df = feature_table(batch, {name: cal.meta}, params, cfd={name: cfd}, range_corrections=rc)
                        first_from_cfd = ~np.isfinite(_first_dr(batch))
                        d = df["echo_time_ns"].to_numpy() * RANGE_PER_NS
                        for a in "xy":
                            df[f"echo_{a}"] = (batch.column(f"anchor_{a}").to_numpy(zero_copy_only=False)
                                               + batch.column(f"dir_{a}").to_numpy(zero_copy_only=False) * d)
                        table = pa.Table.from_pandas(df, preserve_index=False)
                        for key, arr in _cfd_columns(batch, cal, cfd, max_echoes, use_rc).items():
                            table = table.append_column(key, arr)
                        if writer is None:
                            writer = pq.ParquetWriter(tmp, table.schema, compression="zstd")
                        writer.write_table(table.cast(writer.schema))
                        n += table.num_rows
                        n_seg += int(df["Apeak"].notna().sum())
                        n_echo += int(table.column("n_cfd_echoes").to_numpy().sum())
                        n_cfd_first += int(first_from_cfd.sum())
                        bar.update(batch.num_rows)
            if writer is None:
                raise WaveforestError(f"{', '.join(map(str, pulse_paths))}: no pulses")
        finally:
            if writer is not None:
                writer.close()
    if n_cfd_first:
        warnings.warn(f"dataset {name}: {n_cfd_first:,} pulse(s) without a DR echo; their first CFD echo is used",
                      WaveforestWarning, stacklevel=2)
    return CFDFeatures(Path(out_path), n, n_seg, n_echo, n_cfd_first)


def _first_dr(batch: pa.Table) -> np.ndarray:
    """First DR echo time of each pulse, ns (NaN without)."""
    te, tl = list_to_padded(batch.column("echo_time_ns"), dtype=np.float64)
    out = np.full(batch.num_rows, np.nan)
    if te.shape[1]:
        out[tl > 0] = te[tl > 0, 0]
    return out


@click.command()
@click.argument("pulses", type=EXISTING_FILE, nargs=-1, required=True)
@click.option("--calibration", "calibration", type=EXISTING_FILE, multiple=True,
              help="Calibration JSON(s) giving each dataset's noise mean and SD (repeatable).")
@click.option("--cfd", "cfd", type=EXISTING_FILE, default=None,
              help="Instead of calibrations: the JSON of `waveforest tune-cfd` (noise, CFD, range correction); "
                   "adds every CFD echo (time, range, XYZ, amplitude) as list columns.")
@click.option("--out", "out", type=OUT_FILE, required=True, help="Feature table (Parquet).")
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
@stage_options
def features(pulses, calibration, cfd, out, progress, cfg):
    """First-echo waveform features (Npeaks, Apeak, FWHM, E, H) of real or simulated pulses (docs/method.md §(h)).

    PULSES are one or more pulse tables (e.g. the chunks of `waveforest simulate`). Give either
    --calibration (the study) or --cfd (one file tuned by `waveforest tune-cfd`, no targets needed).
    """
    if bool(calibration) == bool(cfd):
        raise click.UsageError("give either --calibration (one or more) or --cfd, not both and not neither")
    if cfd:
        with warnings_to_stderr():
            res = run_cfd(list(pulses), cfd, out, cfg, progress=progress)
        click.echo(f"features: {res.n_pulses:,} pulses ({res.n_with_segment:,} with a first-echo segment, "
                   f"{res.n_cfd_echoes:,} CFD echoes) from {len(pulses)} file(s) -> {out}")
        return
    df = run(list(pulses), list(calibration), out, cfg, progress=progress)
    ok = int(df["Apeak"].notna().sum()) if len(df) else 0
    click.echo(f"features: {len(df)} pulses ({ok} with a first-echo segment) from {len(pulses)} file(s) -> {out}")
