"""The AGC fit of one dataset's pulse table, Eq. 1 (docs/method.md §(b)).

:func:`fit_agc` streams the table once: the AGC values, the noise floor n0 and the fit
statistic of the pulses on AGC targets (:func:`scan_pulses`); keeps the unclipped target
pulses in passes (:func:`fit_pulses`); fits a and b (:func:`fit_law`). :func:`write_normalised`
streams it a second time and writes every pulse normalised by the fit. The pure kernels are in
:mod:`waveforest.sensor.agc`.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.io.pulses import check_pulses, iter_pulses, list_to_padded, single_dataset
from waveforest.io.results import agc_schema_metadata
from waveforest.io.tables import dataset_year
from waveforest.sensor.agc import (
    SCAN_COLUMNS,
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


@dataclass(frozen=True)
class AGCSettings:
    """The fit of Eq. 1 (config section ``agc``, with ``calibrate.noise_tail`` and ``sensor.digitizer_max``).

    statistic : ``energy`` | ``peak``, the echo amplitude whose nested CV is minimised.
    energy_half_window_ns : half width of the energy window, ns.  b : fixed b, or None to fit
    it.  b_bounds : (lo, hi) search interval of b.  grid_points : b values scanned.
    min_pulses_per_target : fewest usable pulses of a target pass.  pass_gap_s : GPS-time gap
    between passes, s.  noise_tail : last samples of a waveform that give n0.
    digitizer_max : clipping level, DN.
    """

    statistic: str
    energy_half_window_ns: float
    b: float | None
    b_bounds: tuple
    grid_points: int
    min_pulses_per_target: int
    pass_gap_s: float
    noise_tail: int
    digitizer_max: float


@dataclass
class PulseScan:
    """What the first pass over a pulse table gathers (:func:`scan_pulses`)."""

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


def scan_pulses(pulses_path: Path, targets, datasets, settings: AGCSettings, batch_rows: int,
                progress: bool) -> PulseScan:
    """Pass 1: the AGC values, the noise tails and the fit statistic of the pulses on AGC targets.

    ``fit_rows`` holds per batch (raw peak, window sum, window count, AGC, target index, GPS
    time) of the target pulses. Raises WaveforestError for an empty table, more than one
    dataset, or no samples to estimate n0.
    """
    from tqdm import tqdm

    tail = settings.noise_tail
    statistic = settings.statistic  # energy | peak (the schema's enum)
    half_window_ns = settings.energy_half_window_ns
    names: set = set()
    agc_sum = agc_n = 0.0
    agc_min, agc_max = np.inf, -np.inf
    n_total = n_missing = 0
    tail_sum = tail_sq = tail_n = 0.0
    fit_rows: list[tuple] = []
    year_cache: dict = {}
    batches = iter_pulses(pulses_path, batch_rows, columns=SCAN_COLUMNS)
    for batch in tqdm(batches, desc="agc: read", unit="batch", disable=not progress, file=None):
        ds = batch.column("dataset").to_numpy(zero_copy_only=False)
        names.update(set(np.unique(ds.astype(str))))
        name = single_dataset(names, pulses_path)
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
    name = single_dataset(names, pulses_path)
    if tail_n < 2:
        raise WaveforestError(f"{pulses_path}: no waveform samples to estimate the noise floor n0")
    n0 = tail_sum / tail_n
    noise_sd = math.sqrt(max(tail_sq / tail_n - n0**2, 0.0) * tail_n / (tail_n - 1))
    return PulseScan(name, year_cache[name], agc_sum, agc_n, np.array([agc_min, agc_max]), n_total, n_missing,
                     n0, noise_sd, fit_rows)


@dataclass
class FitPulses:
    """The target pulses the fit uses, one group per target pass (:func:`fit_pulses`)."""

    amps: np.ndarray
    agc: np.ndarray
    target: np.ndarray
    group: np.ndarray
    n_saturated: int
    n_per_target: dict
    n_per_pass: dict
    pass_label: dict


def fit_pulses(scan: PulseScan, targets, settings: AGCSettings) -> FitPulses:
    """Target pulses without clipping, with AGC and statistic, in passes of >= ``min_pulses_per_target``.

    The statistic is taken above n0 (sum - count x n0); passes are split at gaps of
    ``pass_gap_s`` in GPS time, over all target pulses (clipped ones included).
    """
    dmax = settings.digitizer_max

    def cat(i, dtype=np.float64):
        return np.concatenate([r[i] for r in scan.fit_rows]) if scan.fit_rows else np.empty(0, dtype=dtype)

    raw_max, sums, counts, fagc, ftgt, fgps = cat(0), cat(1), cat(2, np.int64), cat(3), cat(4, np.int64), cat(5)
    fpass = target_passes(fgps, ftgt, settings.pass_gap_s)
    sat = raw_max >= dmax
    keep = ~sat & np.isfinite(fagc) & np.isfinite(sums)
    amps = sums[keep] - counts[keep] * scan.n0
    fagc, ftgt, fpass = fagc[keep], ftgt[keep], fpass[keep]
    fgrp = ftgt * (int(fpass.max()) + 1 if fpass.size else 1) + fpass  # one group per target pass
    ids, counts = np.unique(fgrp, return_counts=True)
    good = np.isin(fgrp, ids[counts >= settings.min_pulses_per_target])
    amps, fagc, ftgt, fpass, fgrp = amps[good], fagc[good], ftgt[good], fpass[good], fgrp[good]
    tid = targets["target_id"].to_numpy()
    n_per_target = {str(tid[k]): int(c) for k, c in zip(*np.unique(ftgt, return_counts=True))}
    pass_label = {int(g): f"{tid[k]}#{p}" for g, k, p in zip(fgrp, ftgt, fpass)}
    n_per_pass = {pass_label[int(g)]: int(c) for g, c in zip(*np.unique(fgrp, return_counts=True))}
    return FitPulses(amps, fagc, ftgt, fgrp, int(sat.sum()), n_per_target, n_per_pass, pass_label)


def fit_law(scan: PulseScan, fp: FitPulses, settings: AGCSettings, pulses_path) -> tuple:
    """a, b, CV before / after, the CV(b) grid and curve, and the feasible b bounds of Eq. 1.

    a is the mean AGC; b is ``settings.b`` if set, else :func:`fit_b` over ``b_bounds``. No AGC
    values: all NaN (warns). Raises WaveforestError when too few target pulses are left to fit b.
    """
    fixed = settings.b
    bounds = settings.b_bounds
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
        b, cv_after, grid, curve = fit_b(amps, fagc, fgrp, a, bounds, settings.grid_points, all_agc=all_agc)
    cv_before = nested_cv(amps, fagc, fgrp, a, 0.0) if amps.size else float("nan")
    return a, b, cv_before, cv_after, grid, curve, eff_bounds


def fit_agc(pulses_path: Path, targets, datasets, settings: AGCSettings, batch_rows: int = 65536,
            progress: bool = True) -> AGCFit:
    """The AGC fit of one dataset's pulse table: :func:`scan_pulses`, :func:`fit_pulses`, :func:`fit_law`.

    ``targets``, ``datasets``: DataFrames of targets.csv / datasets.csv (see
    :mod:`waveforest.sensor.targets`). Per-target and per-pass CVs are keyed by target id and
    ``{target_id}#{pass}``.
    """
    scan = scan_pulses(pulses_path, targets, datasets, settings, batch_rows, progress)
    fp = fit_pulses(scan, targets, settings)
    a, b, cv_before, cv_after, grid, curve, eff_bounds = fit_law(scan, fp, settings, pulses_path)
    amps, fagc, ftgt, fgrp = fp.amps, fp.agc, fp.target, fp.group
    tid = targets["target_id"].to_numpy()
    label = lambda d: {str(tid[k]): v for k, v in d.items()}  # noqa: E731
    plabel = lambda d: {fp.pass_label[int(g)]: v for g, v in d.items()}  # noqa: E731
    have_a, have_b = amps.size and np.isfinite(a), amps.size and np.isfinite(b)
    return AGCFit(
        dataset=str(scan.name), year=int(scan.year), a=float(a), b=float(b), n0=float(scan.n0),
        noise_sd=float(scan.noise_sd), b_bounds=tuple(float(v) for v in eff_bounds), cv_before=float(cv_before),
        cv_after=float(cv_after), n_pulses_total=int(scan.n_total), n_fit_pulses=int(amps.size),
        n_missing_agc=int(scan.n_missing), n_saturated=fp.n_saturated, n_per_target=fp.n_per_target,
        cv_per_target_before=label(cv_per_group(amps, fagc, ftgt, a, 0.0)) if have_a else {},
        cv_per_target_after=label(cv_per_group(amps, fagc, ftgt, a, b)) if have_b else {},
        pass_gap_s=settings.pass_gap_s, n_per_pass=fp.n_per_pass,
        cv_per_pass_before=plabel(cv_per_group(amps, fagc, fgrp, a, 0.0)) if have_a else {},
        cv_per_pass_after=plabel(cv_per_group(amps, fagc, fgrp, a, b)) if have_b else {},
        b_grid=grid.tolist(), cv_grid=curve.tolist(), fixed_b=settings.b is not None,
        statistic=settings.statistic,
    )


def write_normalised(pulses_path: Path, fit: AGCFit, out_path, batch_rows: int = 65536, progress: bool = True) -> None:
    """Pass 2: every pulse normalised by Eq. 1 (:func:`normalise_pulses`), written atomically
    with the fit's {dataset, a, b, n0} in the schema metadata (:func:`.io.results.agc_schema_metadata`)."""
    from tqdm import tqdm

    meta = agc_schema_metadata(fit.dataset, fit.a, fit.b, fit.n0)
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
