"""The ``agc`` stage: fit the AGC law of Eq. 1 on the AGC targets and normalise every pulse
(docs/method.md §(b)); the pure kernels are in :mod:`waveforest.sensor.agc`."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path, write_json
from waveforest.cliutil import OUT_FILE, dataset_pulses_options, stage_options
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.io.pulses import check_pulses, iter_pulses, list_to_padded
from waveforest.io.tables import dataset_year, read_datasets, read_targets
from waveforest.report.plots import plot_cv_curve
from waveforest.sensor.agc import (
    _PASS1_COLUMNS,
    AGC_METADATA_KEY,
    AGCFit,
    agc_gain,
    cv_per_group,
    feasible_b_bounds,
    fit_b,
    nested_cv,
    normalise_pulses,
    peak_amplitudes,
    target_passes,
    window_sums,
)
from waveforest.sensor.noise import tail_samples
from waveforest.sensor.targets import pulse_targets


def _single_dataset(names: set, path) -> str:
    if len(names) != 1:
        raise WaveforestError(
            f"{path}: holds datasets {', '.join(sorted(map(str, names))) or '(none)'}; expected exactly one "
            "(run the step once per dataset file)")
    return next(iter(names))


@dataclass
class _Scan:
    """What the first pass over a pulse table gathers (:func:`_scan_pulses`)."""

    name: str
    year: int
    agc_sum: float
    agc_n: float
    agc_range: np.ndarray
    n_total: int
    n_missing: int
    n0: float
    noise_sd: float
    fit_rows: list


def _scan_pulses(pulses_path: Path, targets, datasets, cfg: dict, batch_rows: int, progress: bool) -> _Scan:
    """Pass 1: the AGC values, the noise tails and the fit statistic of the pulses on AGC targets.

    ``fit_rows`` holds per batch (raw peak, window sum, window count, AGC, target index, GPS
    time) of the target pulses. Raises WaveforestError for an empty table, more than one
    dataset, or no samples to estimate n0.
    """
    from tqdm import tqdm

    sec = cfg["agc"]
    tail = int(cfg["calibrate"]["noise_tail"])
    statistic = str(sec["statistic"])  # energy | peak (the schema's enum)
    half_window_ns = float(sec["energy_half_window_ns"])
    names: set = set()
    agc_sum = agc_n = 0.0
    agc_min, agc_max = np.inf, -np.inf
    n_total = n_missing = 0
    tail_sum = tail_sq = tail_n = 0.0
    fit_rows: list[tuple] = []
    year_cache: dict = {}
    batches = iter_pulses(pulses_path, batch_rows, columns=_PASS1_COLUMNS)
    for batch in tqdm(batches, desc="agc: read", unit="batch", disable=not progress, file=None):
        ds = batch.column("dataset").to_numpy(zero_copy_only=False)
        names.update(set(np.unique(ds.astype(str))))
        name = _single_dataset(names, pulses_path)
        if name not in year_cache:
            year_cache[name] = dataset_year(datasets, name)
        agc = batch.column("agc").to_numpy(zero_copy_only=False).astype(np.float64)
        fin = np.isfinite(agc)
        n_total += agc.size
        n_missing += int((~fin).sum())
        if fin.any():
            agc_sum += agc[fin].sum()
            agc_n += fin.sum()
            agc_min, agc_max = min(agc_min, agc[fin].min()), max(agc_max, agc[fin].max())
        samples, lens = list_to_padded(batch.column("samples"))
        if samples.shape[1]:
            tv, ok = tail_samples(samples, lens, tail)
            v = tv[ok]
            tail_sum += v.sum()
            tail_sq += (v**2).sum()
            tail_n += v.size
        tidx = pulse_targets(batch, targets, year_cache[name])
        on = tidx >= 0
        on[on] = targets["agc"].to_numpy(dtype=bool)[tidx[on]]
        if on.any():
            raw_max = peak_amplitudes(samples[on], lens[on], 0.0)
            if statistic == "energy":
                dt = batch.column("sampling_ns").to_numpy(zero_copy_only=False).astype(np.float64)[on]
                sums, counts = window_sums(samples[on], lens[on], np.maximum(np.rint(half_window_ns / dt), 1))
            else:
                sums, counts = raw_max, np.ones(raw_max.size, np.int64)
            gps = batch.column("gps_time").to_numpy(zero_copy_only=False).astype(np.float64)
            fit_rows.append((raw_max, sums, counts, agc[on], tidx[on], gps[on]))
    if not names:
        raise WaveforestError(f"{pulses_path}: the pulse table is empty")
    name = _single_dataset(names, pulses_path)
    if tail_n < 2:
        raise WaveforestError(f"{pulses_path}: no waveform samples to estimate the noise floor n0")
    n0 = tail_sum / tail_n
    noise_sd = math.sqrt(max(tail_sq / tail_n - n0**2, 0.0) * tail_n / (tail_n - 1))
    return _Scan(name, year_cache[name], agc_sum, agc_n, np.array([agc_min, agc_max]), n_total, n_missing,
                 n0, noise_sd, fit_rows)


@dataclass
class _FitPulses:
    """The target pulses the fit uses, one group per target pass (:func:`_fit_pulses`)."""

    amps: np.ndarray
    agc: np.ndarray
    target: np.ndarray
    group: np.ndarray
    n_saturated: int
    n_per_target: dict
    n_per_pass: dict
    pass_label: dict


def _fit_pulses(scan: _Scan, targets, cfg: dict) -> _FitPulses:
    """Target pulses without clipping, with AGC and statistic, in passes of >= ``agc.min_pulses_per_target``.

    The statistic is taken above n0 (sum - count x n0); passes are split at gaps of
    ``agc.pass_gap_s`` in GPS time, over all target pulses (clipped ones included).
    """
    sec = cfg["agc"]
    dmax = float(cfg["sensor"]["digitizer_max"])

    def cat(i, dtype=np.float64):
        return np.concatenate([r[i] for r in scan.fit_rows]) if scan.fit_rows else np.empty(0, dtype=dtype)

    raw_max, sums, counts, fagc, ftgt, fgps = cat(0), cat(1), cat(2, np.int64), cat(3), cat(4, np.int64), cat(5)
    fpass = target_passes(fgps, ftgt, float(sec["pass_gap_s"]))
    sat = raw_max >= dmax
    keep = ~sat & np.isfinite(fagc) & np.isfinite(sums)
    amps = sums[keep] - counts[keep] * scan.n0
    fagc, ftgt, fpass = fagc[keep], ftgt[keep], fpass[keep]
    fgrp = ftgt * (int(fpass.max()) + 1 if fpass.size else 1) + fpass  # one group per target pass
    ids, counts = np.unique(fgrp, return_counts=True)
    good = np.isin(fgrp, ids[counts >= int(sec["min_pulses_per_target"])])
    amps, fagc, ftgt, fpass, fgrp = amps[good], fagc[good], ftgt[good], fpass[good], fgrp[good]
    tid = targets["target_id"].to_numpy()
    n_per_target = {str(tid[k]): int(c) for k, c in zip(*np.unique(ftgt, return_counts=True))}
    pass_label = {int(g): f"{tid[k]}#{p}" for g, k, p in zip(fgrp, ftgt, fpass)}
    n_per_pass = {pass_label[int(g)]: int(c) for g, c in zip(*np.unique(fgrp, return_counts=True))}
    return _FitPulses(amps, fagc, ftgt, fgrp, int(sat.sum()), n_per_target, n_per_pass, pass_label)


def _fit_law(scan: _Scan, fp: _FitPulses, cfg: dict, pulses_path) -> tuple:
    """a, b, CV before / after, the CV(b) grid and curve, and the feasible b bounds of Eq. 1.

    a is the mean AGC; b is ``agc.b`` if set, else :func:`fit_b` over ``agc.b_bounds``. No AGC
    values: all NaN (warns). Raises WaveforestError when too few target pulses are left to fit b.
    """
    sec = cfg["agc"]
    fixed = sec["b"]
    bounds = tuple(sec["b_bounds"])
    amps, fagc, fgrp = fp.amps, fp.agc, fp.group
    if scan.agc_n == 0:
        warnings.warn(f"{pulses_path}: dataset {scan.name} has no AGC values; waveforms are not normalised "
                      "(b = NaN)", WaveforestWarning, stacklevel=3)
        nan = float("nan")
        return nan, nan, nan, nan, np.empty(0), np.empty(0), (nan, nan)
    a = scan.agc_sum / scan.agc_n
    all_agc = scan.agc_range
    eff_bounds = feasible_b_bounds(all_agc, a, bounds)
    if scan.n_missing:
        warnings.warn(f"{pulses_path}: {scan.n_missing} pulse(s) without AGC are left unnormalised",
                      WaveforestWarning, stacklevel=3)
    if fixed is not None:
        b, grid, curve = float(fixed), np.empty(0), np.empty(0)
        agc_gain(all_agc, a, b)  # raises if the fixed b makes a gain <= 0
        cv_after = nested_cv(amps, fagc, fgrp, a, b) if amps.size else float("nan")
    else:
        if amps.size - len(fp.n_per_target) < 2:
            raise WaveforestError(
                f"dataset {scan.name}: too few pulses on AGC targets (targets.csv rows with agc = 1 and year "
                f"{scan.year}; found {amps.size} usable pulses on {len(fp.n_per_target)} target(s)); set agc.b "
                "in the config to use a fixed b instead")
        b, cv_after, grid, curve = fit_b(amps, fagc, fgrp, a, bounds, int(sec["grid_points"]), all_agc=all_agc)
    cv_before = nested_cv(amps, fagc, fgrp, a, 0.0) if amps.size else float("nan")
    return a, b, cv_before, cv_after, grid, curve, eff_bounds


def _write_normalised(pulses_path: Path, fit: AGCFit, out_path, batch_rows: int, progress: bool) -> None:
    """Pass 2: every pulse normalised by Eq. 1 (:func:`normalise_pulses`), written atomically
    with the fit's {dataset, a, b, n0} under :data:`AGC_METADATA_KEY` in the schema metadata."""
    from tqdm import tqdm

    meta = {AGC_METADATA_KEY: json.dumps({"dataset": fit.dataset, "a": fit.a, "b": fit.b, "n0": fit.n0}).encode()}
    with atomic_path(Path(out_path)) as tmp:
        writer = None
        try:
            for batch in tqdm(iter_pulses(pulses_path, batch_rows), desc="agc: normalise", unit="batch",
                              disable=not progress):
                batch = normalise_pulses(check_pulses(batch, pulses_path), fit.a, fit.b, fit.n0)
                if writer is None:
                    writer = pq.ParquetWriter(tmp, batch.schema.with_metadata(meta), compression="zstd")
                writer.write_table(batch.cast(writer.schema))
        finally:
            if writer is not None:
                writer.close()


def run(pulses_path, targets, datasets, out_path, fit_path, cfg: dict, *, plot_path=None,
        batch_rows: int = 65536, progress: bool = True) -> AGCFit:
    """The ``agc`` stage: fit b on the AGC targets, normalise every pulse, write both outputs.

    Eq. 1 (docs/method.md §(b)): pass 1 reads the AGC values, the noise floor n0 and the fit
    statistic of the target pulses; the fit; pass 2 writes the normalised pulses.

    Parameters
    ----------
    pulses_path : pulse table of one dataset (Parquet).  targets, datasets : DataFrames of
    targets.csv / datasets.csv (see :mod:`waveforest.sensor.targets`).  out_path : normalised
    pulse table (Parquet, with :data:`GAIN_COLUMN` and schema metadata a, b, n0).
    fit_path : JSON of the :class:`AGCFit`.  cfg : validated config (:func:`waveforest.config.validate`;
    sections agc, calibrate, sensor).
    plot_path : optional PNG of CV(b).

    Returns
    -------
    AGCFit

    Raises
    ------
    WaveforestError
        Missing or empty table, several datasets, no samples for n0, too few target pulses to fit b.
    """
    pulses_path = Path(pulses_path)
    if not pulses_path.exists():
        raise WaveforestError(f"{pulses_path}: no such file")
    scan = _scan_pulses(pulses_path, targets, datasets, cfg, batch_rows, progress)
    fp = _fit_pulses(scan, targets, cfg)
    a, b, cv_before, cv_after, grid, curve, eff_bounds = _fit_law(scan, fp, cfg, pulses_path)
    amps, fagc, ftgt, fgrp = fp.amps, fp.agc, fp.target, fp.group
    tid = targets["target_id"].to_numpy()
    label = lambda d: {str(tid[k]): v for k, v in d.items()}  # noqa: E731
    plabel = lambda d: {fp.pass_label[int(g)]: v for g, v in d.items()}  # noqa: E731
    have_a, have_b = amps.size and np.isfinite(a), amps.size and np.isfinite(b)
    fit = AGCFit(
        dataset=str(scan.name), year=int(scan.year), a=float(a), b=float(b), n0=float(scan.n0),
        noise_sd=float(scan.noise_sd), b_bounds=tuple(float(v) for v in eff_bounds), cv_before=float(cv_before),
        cv_after=float(cv_after), n_pulses_total=int(scan.n_total), n_fit_pulses=int(amps.size),
        n_missing_agc=int(scan.n_missing), n_saturated=fp.n_saturated, n_per_target=fp.n_per_target,
        cv_per_target_before=label(cv_per_group(amps, fagc, ftgt, a, 0.0)) if have_a else {},
        cv_per_target_after=label(cv_per_group(amps, fagc, ftgt, a, b)) if have_b else {},
        pass_gap_s=float(cfg["agc"]["pass_gap_s"]), n_per_pass=fp.n_per_pass,
        cv_per_pass_before=plabel(cv_per_group(amps, fagc, fgrp, a, 0.0)) if have_a else {},
        cv_per_pass_after=plabel(cv_per_group(amps, fagc, fgrp, a, b)) if have_b else {},
        b_grid=grid.tolist(), cv_grid=curve.tolist(), fixed_b=cfg["agc"]["b"] is not None,
        statistic=str(cfg["agc"]["statistic"]),
    )
    _write_normalised(pulses_path, fit, out_path, batch_rows, progress)
    write_json(fit.to_dict(), fit_path)
    if plot_path is not None and len(fit.b_grid):
        plot_cv_curve(fit, plot_path)
    return fit


def read_agc_metadata(path) -> dict:
    """The {dataset, a, b, n0} metadata of a normalised pulse table ({} if absent)."""
    md = pq.read_schema(path).metadata or {}
    if AGC_METADATA_KEY in md:
        return json.loads(md[AGC_METADATA_KEY])
    return {}


@click.command()
@dataset_pulses_options
@click.option("--out", "out", type=OUT_FILE, required=True, help="Normalised pulse table (Parquet).")
@click.option("--fit", "fit", type=OUT_FILE, required=True, help="Fit of Eq. 1 (JSON: a, b, CV before/after, ...).")
@click.option("--plot", "plot", type=OUT_FILE, default=None, help="Optional PNG of CV(b).")
@stage_options
def agc(pulses, targets_csv, datasets_csv, out, fit, plot, cfg):
    """Fit the AGC law on AGC targets; normalise waveforms and intensities (docs/method.md §(b), Eq. 1).

    PULSES is the pulse table of one dataset (`waveforest ingest` output).
    """

    res = run(pulses, read_targets(targets_csv), read_datasets(datasets_csv), out, fit, cfg, plot_path=plot)
    click.echo(f"agc: {res.dataset}: a = {res.a:.3f}, b = {res.b:.6f}, nested CV {100 * res.cv_before:.2f} % -> "
               f"{100 * res.cv_after:.2f} % on {res.n_fit_pulses} target pulses; wrote {res.n_pulses_total} pulses "
               f"to {out} and the fit to {fit}")
