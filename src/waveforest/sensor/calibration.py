"""System-waveform calibration from reference targets, Eq. 8 (METHOD.md e).

For a near-level planar target sigma(t) is a single spike of ``sigma = HDRF / pi`` per unit
power (times cos(incidence) if ``calibrate.cos_incidence``), so each target pulse gives

    S_i(t) = (V_i(t) - c-bar) * R_i^2 / sigma_i                                      (8)

with V_i the AGC-normalised waveform resampled to the 0.05-ns grid by linear interpolation,
aligned so that t = 0 is the pulse's first DR echo time (``echo_time_ns[0]``), and R_i its
range. S(t) is the mean of S_i over all pulses of all calibration targets (equal weight per
pulse), its spread the SD over pulses. c-bar and the noise SD come from the last
``calibrate.noise_tail`` samples of the same pulses, taken on the recorded values (the AGC
normalisation is undone for the tails: the AGC does not change the noise).

Pulses whose recorded peak reaches the digitiser maximum (clipped) or whose incidence zenith
exceeds ``calibrate.max_zenith_deg`` are left out.

The same stage checks the CFD against the DR ranges (METHOD.md f) on all target pulses
(calibration and AGC targets): the fraction with |dR| < 0.10 m and the bias, before and
after the amplitude-dependent range correction it fits (:func:`fit_range_correction`).
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..constants import RANGE_PER_NS
from ..errors import WaveforestError
from ..io.tables import iter_pulses, list_to_padded
from . import _checks
from .agc import GAIN_COLUMN, _single_dataset, read_agc_metadata, write_json
from .cfd import RangeCorrection, detect_echoes, fit_range_correction
from .noise import noise_stats
from .params import CFD_CHECK_M, FINE_NS, RANGE_GATE_M, CFDParams
from .system_waveform import SystemWaveform
from .targets import dataset_year, pulse_targets, read_datasets, read_targets  # noqa: F401 (re-exported)

_CHUNK = 2048
"""Pulses per block of the vectorised resampling (bounds memory to ~CHUNK x window samples)."""


def calibration_grid(window_ns=(-20.0, 60.0)) -> np.ndarray:
    """The 0.05-ns time grid of S(t) over ``window_ns`` relative to the echo time (t = 0 on it)."""
    lo, hi = float(window_ns[0]), float(window_ns[1])
    if not lo < 0 < hi:
        raise ValueError(f"window_ns must straddle 0 (lo < 0 < hi), got {window_ns}")
    return FINE_NS * np.arange(math.ceil(lo / FINE_NS - 1e-9), math.floor(hi / FINE_NS + 1e-9) + 1)


def resample_aligned(samples, lengths, sampling_ns, echo_time_ns, t_grid) -> np.ndarray:
    """Waveforms linearly resampled at ``echo_time + t_grid`` (NaN outside each record).

    Parameters
    ----------
    samples : (n, n_s) DN.  lengths : (n,).  sampling_ns, echo_time_ns : (n,) ns.  t_grid : (K,) ns.

    Returns
    -------
    (n, K) float64
    """
    x, lens = _checks.waveforms(samples, lengths)
    n = x.shape[0]
    dt = _checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    te = _checks.per_pulse(echo_time_ns, n, "echo_time_ns")
    pos = (te[:, None] + np.asarray(t_grid)[None, :]) / dt[:, None]
    k = np.floor(pos).astype(np.int64)
    last = (lens - 1)[:, None]
    ok = (pos >= 0) & (pos <= last)
    k = np.clip(k, 0, np.maximum(last - 1, 0))
    f = pos - k
    rows = np.arange(n)[:, None]
    x0 = x[rows, k].astype(np.float64)
    x1 = x[rows, np.minimum(k + 1, x.shape[1] - 1)].astype(np.float64)
    out = (1.0 - f) * x0 + f * x1
    return np.where(ok & (lens[:, None] >= 2), out, np.nan)


def calibrate_system_waveform(samples, lengths, sampling_ns, echo_time_ns, range_m, sigma, noise_mean, *,
                              window_ns=(-20.0, 60.0)) -> SystemWaveform:
    """S(t) by Eq. 8 averaged over planar-target pulses (METHOD.md e).

    Parameters
    ----------
    samples : (n, n_s) DN, AGC-normalised waveforms.  lengths : (n,).
    sampling_ns : float or (n,), ns.  echo_time_ns : (n,) first DR echo, ns from the first sample.
    range_m : (n,) m.  sigma : (n,) target cross-section per unit power (HDRF/pi [x cos]).
    noise_mean : float, c-bar, DN.  window_ns : (lo, hi) time span of S(t) around the echo.

    Returns
    -------
    SystemWaveform with s = mean over pulses and s_sd = SD over pulses (NaN with < 2 pulses);
    meta n_pulses.
    """
    x, lens = _checks.waveforms(samples, lengths)
    n = x.shape[0]
    if n == 0:
        raise ValueError("calibrate_system_waveform: no pulses")
    dt = _checks.per_pulse(sampling_ns, n, "sampling_ns", positive=True)
    te = _checks.per_pulse(echo_time_ns, n, "echo_time_ns")
    r = _checks.per_pulse(range_m, n, "range_m", positive=True)
    sg = _checks.per_pulse(sigma, n, "sigma", positive=True)
    t = calibration_grid(window_ns)
    s1 = np.zeros(t.size)
    s2 = np.zeros(t.size)
    cnt = np.zeros(t.size)
    for start in range(0, n, _CHUNK):  # blocks of pulses, each vectorised
        sl = slice(start, start + _CHUNK)
        v = resample_aligned(x[sl], lens[sl], dt[sl], te[sl], t)
        si = (v - noise_mean) * (r[sl] ** 2 / sg[sl])[:, None]
        ok = np.isfinite(si)
        si = np.where(ok, si, 0.0)
        s1 += si.sum(axis=0)
        s2 += (si**2).sum(axis=0)
        cnt += ok.sum(axis=0)
    if (cnt == 0).any():
        raise ValueError("calibrate_system_waveform: some times of the window lie outside every record; "
                         "narrow calibrate.window_ns")
    mean = s1 / cnt
    var = np.where(cnt > 1, (s2 - cnt * mean**2) / np.maximum(cnt - 1, 1), np.nan)
    sd = np.sqrt(np.maximum(var, 0.0))
    return SystemWaveform(t, mean, sd, {"n_pulses": int(n)})


def cfd_check(dr_minus_cfd_m) -> dict:
    """The paper's CFD criterion on dR = DR range - CFD range, m (gated at RANGE_GATE_M)."""
    d = np.asarray(dr_minus_cfd_m, dtype=np.float64)
    d = d[np.isfinite(d) & (np.abs(d) < RANGE_GATE_M)]
    if d.size == 0:
        return {"n": 0, "frac_within_0_10_m": None, "bias_m": None, "sd_m": None}
    return {"n": int(d.size), "frac_within_0_10_m": float(np.mean(np.abs(d) < CFD_CHECK_M)),
            "bias_m": float(d.mean()), "sd_m": float(d.std(ddof=1)) if d.size > 1 else 0.0}


_COLUMNS = ["dataset", "dir_z", "range_m", "sampling_ns", "samples", "echo_x", "echo_y", "echo_time_ns"]


def _gather_target_pulses(path: Path, targets, datasets, batch_rows: int, progress: bool):
    """Target pulses of a one-dataset pulse table: dict of arrays (small: targets only)."""
    from tqdm import tqdm

    names: set = set()
    keep = []
    year = None
    has_gain = GAIN_COLUMN in pq.read_schema(path).names
    cols = _COLUMNS + ([GAIN_COLUMN] if has_gain else [])
    for batch in tqdm(iter_pulses(path, batch_rows, columns=cols), desc="calibrate: read", unit="batch",
                      disable=not progress):
        names.update(set(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str))))
        name = _single_dataset(names, path)
        if year is None:
            year = dataset_year(datasets, name)
        tidx = pulse_targets(batch, targets, year)
        on = np.flatnonzero(tidx >= 0)
        if on.size:
            sub = batch.take(pa.array(on))
            keep.append((sub, tidx[on]))
    if not names:
        raise WaveforestError(f"{path}: the pulse table is empty")
    name = _single_dataset(names, path)
    if not keep:
        return name, year, None
    table = pa.concat_tables([k[0] for k in keep])
    samples, lens = list_to_padded(table.column("samples"))
    te, tl = list_to_padded(table.column("echo_time_ns"), dtype=np.float64)
    t_echo = np.where(tl > 0, te[:, 0] if te.shape[1] else np.nan, np.nan)
    col = lambda c: table.column(c).to_numpy(zero_copy_only=False).astype(np.float64)  # noqa: E731
    data = {
        "samples": samples, "lengths": lens, "t_echo": t_echo, "range_m": col("range_m"),
        "dir_z": col("dir_z"), "sampling_ns": col("sampling_ns"),
        "gain": col(GAIN_COLUMN) if has_gain else np.ones(table.num_rows),
        "target": np.concatenate([k[1] for k in keep]),
    }
    return name, year, data


def run(pulses_path, targets, datasets, out_path, json_path, cfg: dict, *, plot_path=None, agc_fit: dict | None = None,
        batch_rows: int = 65536, progress: bool = True) -> dict:
    """The ``calibrate`` stage: S(t), noise and the CFD/range-correction check of one dataset.

    Parameters
    ----------
    pulses_path : AGC-normalised pulse table of one dataset (the ``agc`` output; a table
        without AGC normalisation is accepted, gain 1).
    targets, datasets : DataFrames of targets.csv and datasets.csv.
    out_path : S(t) Parquet (t_ns, s, s_sd).  json_path : calibration JSON.  plot_path : PNG.
    cfg : loaded config (sections calibrate, sensor).  agc_fit : the ``agc`` JSON (a, b), optional.

    Returns
    -------
    dict, the calibration JSON content.
    """
    pulses_path = Path(pulses_path)
    if not pulses_path.exists():
        raise WaveforestError(f"{pulses_path}: no such file")
    sec = cfg.get("calibrate", {})
    tail = int(sec.get("noise_tail", 50))
    window = tuple(sec.get("window_ns", (-20.0, 60.0)))
    max_zen = float(sec.get("max_zenith_deg", 15.0))
    cos_inc = bool(sec.get("cos_incidence", False))
    min_pulses = int(sec.get("min_pulses", 20))
    dmax = float(cfg.get("sensor", {}).get("digitizer_max", 255))
    cfd = CFDParams.from_config(cfg)
    max_echoes = int(cfg.get("sensor", {}).get("cfd", {}).get("max_echoes", 4))

    meta = read_agc_metadata(pulses_path)
    if agc_fit:
        meta = {**meta, **{k: agc_fit[k] for k in ("a", "b", "n0") if k in agc_fit}}
    name, year, d = _gather_target_pulses(pulses_path, targets, datasets, batch_rows, progress)
    if d is None:
        raise WaveforestError(f"{pulses_path}: no pulse of dataset {name} hits a target of year {year} in targets.csv")
    n0 = float(meta["n0"]) if meta.get("n0") is not None else None
    is_cal = targets["calibration"].to_numpy(dtype=bool)[d["target"]]
    hdrf = targets["hdrf"].to_numpy(np.float64)[d["target"]]
    cos_t = np.clip(-d["dir_z"], -1.0, 1.0)
    zen_ok = np.degrees(np.arccos(np.abs(cos_t))) <= max_zen + 1e-9
    raw_peak = np.nanmax(np.where(np.arange(d["samples"].shape[1])[None, :] < d["lengths"][:, None],
                                  d["samples"], -np.inf), axis=1).astype(np.float64)
    if n0 is not None:
        raw_peak = (raw_peak - n0) * d["gain"] + n0
    not_sat = raw_peak < dmax - 0.5
    usable = np.isfinite(d["t_echo"]) & np.isfinite(d["range_m"]) & (d["range_m"] > 0) & (d["lengths"] >= 2)
    cal = is_cal & (hdrf > 0) & zen_ok & not_sat & usable
    if cal.sum() < min_pulses:
        raise WaveforestError(
            f"dataset {name}: {int(cal.sum())} usable pulse(s) on calibration targets (targets.csv rows with "
            f"calibration = 1 and year {year}; usable = a first DR echo, a finite range_m (sensor position known), "
            f"incidence zenith <= calibrate.max_zenith_deg, peak below the digitiser maximum); at least "
            f"calibrate.min_pulses = {min_pulses} are needed")
    idx = np.flatnonzero(cal)
    if n0 is not None:
        noise = noise_stats(d["samples"][idx], d["lengths"][idx], tail, gain=d["gain"][idx], n0=n0)
    else:
        noise = noise_stats(d["samples"][idx], d["lengths"][idx], tail)
    sigma = hdrf[idx] / math.pi * (np.abs(cos_t[idx]) if cos_inc else 1.0)
    system = calibrate_system_waveform(d["samples"][idx], d["lengths"][idx], d["sampling_ns"][idx], d["t_echo"][idx],
                                       d["range_m"][idx], sigma, noise.mean, window_ns=window)
    fwhm = system.fwhm_ns
    if not np.isfinite(fwhm):
        raise WaveforestError(f"dataset {name}: the calibrated S(t) has no defined FWHM; widen calibrate.window_ns")
    system.meta.update({"dataset": name, "year": int(year)})

    # CFD vs DR ranges on all usable target pulses (METHOD.md f)
    rc_cfd = cfd.resolved(fwhm)
    chk = np.flatnonzero(usable & zen_ok & not_sat)
    ech = detect_echoes(d["samples"][chk], d["lengths"][chk], d["sampling_ns"][chk], noise.mean, noise.sd, rc_cfd,
                        max_echoes)
    dr = (d["t_echo"][chk] - ech.times_ns[:, 0]) * RANGE_PER_NS
    amp = ech.amplitudes[:, 0]
    gate = np.isfinite(dr) & (np.abs(dr) < RANGE_GATE_M)
    corr = fit_range_correction(amp[gate], dr[gate], n_bins=int(sec.get("range_correction_bins", 8)),
                                min_per_bin=int(sec.get("range_correction_min_pulses", 20)))
    dr_after = dr - corr(amp)
    per_target = {}
    tid = targets["target_id"].to_numpy()
    for k, c in zip(*np.unique(d["target"][idx], return_counts=True)):
        per_target[str(tid[k])] = int(c)

    result = {
        "dataset": name, "year": int(year),
        "noise_mean": noise.mean, "noise_sd": noise.sd, "noise_sd_analog": noise.sd_analog,
        "noise_lag1": noise.lag1, "noise_tail": tail, "noise_quantised": noise.quantised,
        "fwhm_ns": fwhm, "energy": system.energy, "peak": system.peak, "t_peak_ns": system.t_peak_ns,
        "n_pulses": int(idx.size), "n_per_target": per_target,
        "a": meta.get("a"), "b": meta.get("b"), "n0": meta.get("n0"),
        "sampling_ns": float(np.median(d["sampling_ns"][idx])),
        "window_ns": list(window), "cos_incidence": cos_inc,
        "cfd": {"fraction": rc_cfd.fraction, "delay_ns": rc_cfd.delay_ns, "arming_sd": rc_cfd.arming_sd,
                "dead_time_ns": rc_cfd.dead_time_ns},
        "range_correction": corr.to_dict(),
        "cfd_check_before": cfd_check(dr), "cfd_check_after": cfd_check(dr_after),
        "system_waveform": Path(out_path).name,
    }
    if result["cfd_check_after"]["n"] and result["cfd_check_after"]["frac_within_0_10_m"] < 0.95:
        warnings.warn(f"dataset {name}: CFD vs DR ranges: only {result['cfd_check_after']['frac_within_0_10_m']:.1%} "
                      "within 0.10 m (the paper's criterion is > 95 %); consider tuning sensor.cfd", stacklevel=2)
    system.meta.update({k: result[k] for k in ("noise_mean", "noise_sd", "n_pulses")})
    system.save(out_path)
    write_json(result, json_path)
    if plot_path is not None:
        from .plots import plot_system_waveform

        plot_system_waveform(system, plot_path, title=f"S(t) of {name} ({idx.size} pulses)")
    return result


def load_calibration(path) -> dict:
    """A calibration JSON written by the ``calibrate`` stage (checked for the noise keys)."""
    path = Path(path)
    if not path.exists():
        raise WaveforestError(f"{path}: no such calibration file")
    try:
        d = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise WaveforestError(f"{path}: not valid JSON ({exc})") from None
    missing = [k for k in ("dataset", "noise_mean", "noise_sd") if d.get(k) is None]
    if missing:
        raise WaveforestError(f"{path}: calibration lacks {', '.join(missing)}")
    return d


def range_correction_of(calibration: dict) -> RangeCorrection:
    """The range correction stored in a calibration JSON (identity if absent)."""
    return RangeCorrection.from_dict(calibration.get("range_correction"))
