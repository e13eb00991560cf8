"""Feature tables of pulse files: the first-echo features of docs/method.md §(h), per pulse.

Two forms: with the study's calibration JSONs (:func:`calibrated_features`, one DataFrame), and
with the JSON of ``tune-cfd`` for a user's own file (:func:`cfd_features`, streamed into Parquet),
which adds the first echo's x and y and every echo of the tuned CFD, range-corrected, as list
columns (:data:`CFD_COLUMNS`).
"""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path
from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.io.pulses import check_pulses, iter_pulses, list_to_padded, padded_to_list
from waveforest.sensor.calibration import Calibration, load_calibration
from waveforest.sensor.cfd import detect_echoes
from waveforest.sensor.features import FEATURE_NAMES, feature_table
from waveforest.sensor.params import CFDParams, FeatureParams

CFD_COLUMNS = ("cfd_time_ns", "cfd_range_m", "cfd_x", "cfd_y", "cfd_z", "cfd_amplitude")
"""List columns of :func:`cfd_features`: every echo of the tuned CFD (range-corrected time from
the first sample, ns; range from the sensor, m, NaN if the sensor is unknown; position, m;
amplitude above the noise mean, DN)."""

CFD_BATCH_ROWS = 8192
"""Pulses per batch of :func:`cfd_features` (8192 pulses of 256 samples take ~100 MB)."""


@dataclass(frozen=True)
class FeatureTableSettings:
    """Settings of a feature table (config ``sensor.features``, ``sensor.cfd``).

    features : the first-echo feature settings.  cfd : the CFD of a calibration that stores
    none.  range_correction : apply the calibration's range correction to CFD echoes.
    max_echoes : CFD echoes kept per pulse (:func:`cfd_features`).
    """

    features: FeatureParams
    cfd: CFDParams
    range_correction: bool
    max_echoes: int


@dataclass(frozen=True)
class CFDFeatures:
    """What :func:`cfd_features` wrote: rows, rows with a first-echo segment, CFD echoes, rows whose
    first echo came from the CFD (no DR echo)."""

    out: Path
    n_pulses: int
    n_with_segment: int
    n_cfd_echoes: int
    n_first_from_cfd: int


def calibrated_features(pulse_paths, calibration_paths, settings: FeatureTableSettings, *, batch_rows: int = 65536,
                        progress: bool = True) -> pd.DataFrame:
    """First-echo features of one or more pulse tables, each dataset with the noise of its calibration.

    Parameters
    ----------
    pulse_paths : pulse tables (real, AGC-normalised, or simulated chunks) -- read in batches.
    calibration_paths : calibration JSONs (``calibrate`` output) giving each dataset's noise.

    Returns
    -------
    pandas.DataFrame, one row per pulse (:func:`waveforest.sensor.features.feature_table`).
    """
    from tqdm import tqdm

    noise, corrections, cfd = {}, {}, {}
    for p in calibration_paths:
        cal = load_calibration(p)
        noise[cal.dataset] = cal.meta
        cfd[cal.dataset] = cal.cfd or settings.cfd
        if settings.range_correction:
            corrections[cal.dataset] = cal.range_correction_or_identity()
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
            parts.append(feature_table(batch, noise, settings.features, cfd=cfd, range_corrections=corrections))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(
        columns=["dataset", "pulse_id", "source", "n_echoes", "echo_time_ns", *FEATURE_NAMES, "H", "echo_z"])


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


def _first_dr(batch: pa.Table) -> np.ndarray:
    """First DR echo time of each pulse, ns (NaN without)."""
    te, tl = list_to_padded(batch.column("echo_time_ns"), dtype=np.float64)
    out = np.full(batch.num_rows, np.nan)
    if te.shape[1]:
        out[tl > 0] = te[tl > 0, 0]
    return out


def _cfd_feature_batch(batch: pa.Table, cal: Calibration, cfd: CFDParams,
                       settings: FeatureTableSettings) -> tuple[pa.Table, int]:
    """The feature rows of one checked batch of ``cal``'s dataset: the feature table, ``echo_x``,
    ``echo_y`` and the CFD echoes (:data:`CFD_COLUMNS`); and the rows with a first-echo segment."""
    name = cal.dataset
    rc = {name: cal.range_correction_or_identity()} if settings.range_correction else {}
    with warnings.catch_warnings():  # counted and said once by cfd_features
        warnings.simplefilter("ignore", WaveforestWarning)
        df = feature_table(batch, {name: cal.meta}, settings.features, cfd={name: cfd}, range_corrections=rc)
    d = df["echo_time_ns"].to_numpy() * RANGE_PER_NS
    for a in "xy":
        df[f"echo_{a}"] = (batch.column(f"anchor_{a}").to_numpy(zero_copy_only=False)
                           + batch.column(f"dir_{a}").to_numpy(zero_copy_only=False) * d)
    table = pa.Table.from_pandas(df, preserve_index=False)
    for key, arr in _cfd_columns(batch, cal, cfd, settings.max_echoes, settings.range_correction).items():
        table = table.append_column(key, arr)
    return table, int(df["Apeak"].notna().sum())


def cfd_features(pulse_paths, cfd_path, out_path, settings: FeatureTableSettings, *,
                 batch_rows: int = CFD_BATCH_ROWS, progress: bool = True) -> CFDFeatures:
    """First-echo features and every CFD echo of pulse tables, with the JSON of ``tune-cfd``, streamed
    into the Parquet ``out_path`` (atomically, one row group per batch of ``batch_rows`` pulses).

    The first echo is the first DR echo where the pulse has one (§(h)), else the first CFD echo;
    the feature columns are those of :func:`waveforest.sensor.features.feature_table`, then
    ``echo_x``, ``echo_y`` (first-echo position, m), ``n_cfd_echoes`` and :data:`CFD_COLUMNS`.

    Parameters
    ----------
    pulse_paths : pulse tables of the dataset the JSON belongs to.  cfd_path : ``tune-cfd`` JSON
    (noise, fwhm_ns, cfd, range_correction).  out_path : Parquet.
    """
    from tqdm import tqdm

    cal = load_calibration(cfd_path)
    name = cal.dataset
    cfd = (cal.cfd or settings.cfd).resolved(cal.meta.get("fwhm_ns"))
    n = n_seg = n_echo = n_cfd_first = 0
    with atomic_path(out_path) as tmp:
        writer = None
        try:
            for path in map(Path, pulse_paths):
                if not path.exists():
                    raise WaveforestError(f"{path}: no such file")
                total = pq.read_metadata(path).num_rows
                with tqdm(total=total, unit="waveform", unit_scale=True, disable=not progress, file=sys.stderr,
                          desc=f"features {path.name}") as bar:
                    for batch in iter_pulses(path, batch_rows):
                        batch = check_pulses(batch, path)
                        names = set(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str)))
                        if names - {name}:
                            raise WaveforestError(f"{path}: dataset(s) {', '.join(sorted(names - {name}))} are not the "
                                                  f"dataset of {cfd_path} ({name})")
                        table, with_segment = _cfd_feature_batch(batch, cal, cfd, settings)
                        if writer is None:
                            writer = pq.ParquetWriter(tmp, table.schema, compression="zstd")
                        writer.write_table(table.cast(writer.schema))
                        n += table.num_rows
                        n_seg += with_segment
                        n_echo += int(table.column("n_cfd_echoes").to_numpy().sum())
                        n_cfd_first += int((~np.isfinite(_first_dr(batch))).sum())
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
