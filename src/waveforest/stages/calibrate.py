"""The ``calibrate`` stage."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import waveforest.sensor._checks as _checks
from waveforest.atomic import write_json
from waveforest.cliutil import EXISTING_FILE, OUT_FILE, dataset_pulses_options, stage_options
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.io.pulses import iter_pulses, list_to_padded
from waveforest.io.tables import dataset_year, read_datasets, read_targets
from waveforest.report.plots import plot_system_waveform
from waveforest.sensor.agc import GAIN_COLUMN
from waveforest.sensor.calibration import calibrate_system_waveform, cfd_check, model_sensor_effects
from waveforest.sensor.cfd_tuning import WIDTH_EDGES, tune_cfd
from waveforest.sensor.features import first_echo_features
from waveforest.sensor.noise import noise_stats
from waveforest.sensor.params import CFDParams, FeatureParams
from waveforest.sensor.signal import saturation_levels
from waveforest.sensor.system_waveform import SystemWaveform
from waveforest.sensor.targets import pulse_targets
from waveforest.stages.agc import _single_dataset, read_agc_metadata

_COLUMNS = ["dataset", "dir_z", "range_m", "sampling_ns", "samples", "echo_x", "echo_y", "echo_time_ns"]

def _gather_target_pulses(path: Path, targets, datasets, batch_rows: int, progress: bool, extra: int = 0,
                          seed: int = 0):
    """Target pulses of a one-dataset pulse table, and ``extra`` others drawn at random (seeded).

    Returns (dataset, year, dict of arrays or None); ``target`` is -1 for a pulse off the targets.
    """
    from tqdm import tqdm

    names: set = set()
    keep = []
    year = None
    has_gain = GAIN_COLUMN in pq.read_schema(path).names
    cols = _COLUMNS + ([GAIN_COLUMN] if has_gain else [])
    n_rows = pq.read_metadata(path).num_rows
    rng = np.random.default_rng([int(seed), 0xCFD])
    drawn = np.zeros(n_rows, dtype=bool)
    drawn[rng.choice(n_rows, size=min(int(extra), n_rows), replace=False)] = True
    start = 0
    for batch in tqdm(iter_pulses(path, batch_rows, columns=cols), desc="calibrate: read", unit="batch",
                      disable=not progress):
        names.update(set(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str))))
        name = _single_dataset(names, path)
        if year is None:
            year = dataset_year(datasets, name)
        tidx = pulse_targets(batch, targets, year)
        on = np.flatnonzero((tidx >= 0) | drawn[start:start + batch.num_rows])
        start += batch.num_rows
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

@dataclass(frozen=True)
class CalibrationPulses:
    """The calibration-target pulses of one dataset that Eq. 8 averages, with their noise.

    Arrays over the n pulses as :func:`calibrate_system_waveform` takes them (``samples``
    AGC-normalised, DN), and ``gain``, the AGC gain of Eq. 1 of each; ``noise`` from their
    tails; ``window_ns`` of S(t).
    """

    dataset: str
    year: int
    samples: np.ndarray
    lengths: np.ndarray
    sampling_ns: np.ndarray
    t_echo: np.ndarray
    range_m: np.ndarray
    sigma: np.ndarray
    target: np.ndarray
    gain: np.ndarray
    noise: object
    window_ns: tuple

    def system_waveform(self, effects: dict | None = None) -> SystemWaveform:
        """S(t) of the model with ``effects`` (only ``nonlinearity`` and ``trigger_loss`` act
        here; the saturation level L acts after the AGC gain g: L / g in normalised DN)."""
        e = effects or {}
        level = float(e.get("nonlinearity", 0.0))
        system = calibrate_system_waveform(self.samples, self.lengths, self.sampling_ns, self.t_echo, self.range_m,
                                           self.sigma, self.noise.mean, window_ns=self.window_ns,
                                           nonlinearity=saturation_levels(level, self.gain) if level else 0.0,
                                           trigger_loss=float(e.get("trigger_loss", 0.0)))
        if level:
            system.meta["nonlinearity"] = level
        return system

def _target_pulses(pulses_path: Path, targets, datasets, cfg: dict, agc_fit, batch_rows: int, progress: bool,
                   extra: int = 0):
    """The target pulses of a pulse table and ``extra`` random others.

    Returns (CalibrationPulses, dict of arrays of all pulses read, AGC metadata, usable mask:
    a first DR echo and a range, not clipped, and on a target within the zenith limit or off the
    targets).
    """
    if not pulses_path.exists():
        raise WaveforestError(f"{pulses_path}: no such file")
    sec = cfg["calibrate"]
    tail = int(sec["noise_tail"])
    window = tuple(sec["window_ns"])
    max_zen = float(sec["max_zenith_deg"])
    cos_inc = bool(sec["cos_incidence"])
    min_pulses = int(sec["min_pulses"])
    dmax = float(cfg["sensor"]["digitizer_max"])

    meta = read_agc_metadata(pulses_path)
    if agc_fit:
        meta = {**meta, **{k: agc_fit[k] for k in ("a", "b", "n0") if k in agc_fit}}
    name, year, d = _gather_target_pulses(pulses_path, targets, datasets, batch_rows, progress, extra,
                                          int(cfg["seed"]))
    if d is None:
        raise WaveforestError(f"{pulses_path}: no pulse of dataset {name} hits a target of year {year} in targets.csv")
    n0 = float(meta["n0"]) if meta.get("n0") is not None else None
    on_target = d["target"] >= 0
    is_cal = on_target & targets["calibration"].to_numpy(dtype=bool)[d["target"]]
    hdrf = np.where(on_target, targets["hdrf"].to_numpy(np.float64)[d["target"]], np.nan)
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
    pulses = CalibrationPulses(str(name), int(year), d["samples"][idx], d["lengths"][idx], d["sampling_ns"][idx],
                               d["t_echo"][idx], d["range_m"][idx], sigma, d["target"][idx], d["gain"][idx], noise,
                               window)
    return pulses, d, meta, usable & not_sat & (zen_ok | ~on_target)

def read_calibration_pulses(pulses_path, targets, datasets, cfg: dict, *, agc_fit: dict | None = None,
                            batch_rows: int = 65536, progress: bool = False) -> CalibrationPulses:
    """The calibration-target pulses of an AGC-normalised pulse table (the ``agc`` output).

    Parameters as :func:`run`. Raises WaveforestError if too few pulses hit calibration targets.
    """
    return _target_pulses(Path(pulses_path), targets, datasets, cfg, agc_fit, batch_rows, progress)[0]

def _cfd_against_dr(d: dict, checkable, noise, system_fwhm_ns: float, cfg: dict):
    """The CFD (tuned unless ``calibrate.tune_cfd`` is false) on the checkable pulses of ``d``.

    Returns (CFDTuning, on-target mask over those pulses).
    """
    sec = cfg["calibrate"]
    idx = np.flatnonzero(checkable)
    x, lens, dt, te = d["samples"][idx], d["lengths"][idx], d["sampling_ns"][idx], d["t_echo"][idx]
    fp = FeatureParams.from_config(cfg)
    width = first_echo_features(x, lens, dt, te, noise.mean, noise.sd, fp.segment_sd, fp.peak_rise_sd,
                                echo_search_ns=fp.echo_search_ns)["FWHM"]
    armed_sd = noise.sd / _checks.gain_or_one(d["gain"][idx])  # the recorded noise, as the DR circuits see it
    tuning = tune_cfd(x, lens, dt, te, width, noise.mean, armed_sd, CFDParams.from_config(cfg), system_fwhm_ns,
                      tune=bool(sec["tune_cfd"]), n_bins=int(sec["range_correction_bins"]),
                      min_per_bin=int(sec["range_correction_min_pulses"]))
    return tuning, d["target"][idx] >= 0

def run(pulses_path, targets, datasets, out_path, json_path, cfg: dict, *, plot_path=None, agc_fit: dict | None = None,
        batch_rows: int = 65536, progress: bool = True) -> dict:
    """The ``calibrate`` stage: S(t), noise and the CFD/range-correction check of one dataset.

    Parameters
    ----------
    pulses_path : AGC-normalised pulse table of one dataset (the ``agc`` output; a table
        without AGC normalisation is accepted, gain 1).
    targets, datasets : DataFrames of targets.csv and datasets.csv.
    out_path : S(t) Parquet (t_ns, s, s_sd).  json_path : calibration JSON.  plot_path : PNG.
    cfg : validated config (:func:`waveforest.config.validate`; sections calibrate, sensor, seed and the
        sensor effects of simulate.effects).
    agc_fit : the ``agc`` JSON (a, b), optional.

    Returns
    -------
    dict, the calibration JSON content.
    """
    sec = cfg["calibrate"]
    pulses, d, meta, checkable = _target_pulses(Path(pulses_path), targets, datasets, cfg, agc_fit, batch_rows,
                                                progress, extra=int(sec["cfd_pulses"]))
    name, year, noise, window = pulses.dataset, pulses.year, pulses.noise, pulses.window_ns
    effects = model_sensor_effects(cfg)
    system = pulses.system_waveform(effects)  # S(t) of the model that will use it
    fwhm = system.fwhm_ns
    if not np.isfinite(fwhm):
        raise WaveforestError(f"dataset {name}: the calibrated S(t) has no defined FWHM; widen calibrate.window_ns")
    system.meta.update({"dataset": name, "year": int(year)})

    # CFD (tuned) and range correction against the DR ranges (docs/method.md §(f))
    tuning, on_target = _cfd_against_dr(d, checkable, noise, fwhm, cfg)
    ranges = tuning.ranges
    dr, corr = ranges.dr_minus_cfd_m, ranges.correction
    dr_after = ranges.residual_m
    per_target = {}
    tid = targets["target_id"].to_numpy()
    for k, c in zip(*np.unique(pulses.target, return_counts=True)):
        per_target[str(tid[k])] = int(c)

    result = {
        "dataset": name, "year": int(year),
        "noise_mean": noise.mean, "noise_sd": noise.sd, "noise_sd_analog": noise.sd_analog,
        "noise_lag1": noise.lag1, "noise_tail": int(sec["noise_tail"]), "noise_quantised": noise.quantised,
        "fwhm_ns": fwhm, "energy": system.energy, "peak": system.peak, "t_peak_ns": system.t_peak_ns,
        "n_pulses": int(pulses.target.size), "n_per_target": per_target, "model_effects": effects,
        "a": meta.get("a"), "b": meta.get("b"), "n0": meta.get("n0"),
        "sampling_ns": float(np.median(pulses.sampling_ns)),
        "window_ns": list(window), "cos_incidence": bool(sec["cos_incidence"]),
        "cfd": ranges.cfd.to_dict(),
        "cfd_tuning": {"tuned": tuning.tuned, "reason": tuning.reason, "n_pulses": int(on_target.size),
                       "n_off_targets": int((~on_target).sum()),
                       "bias_per_width_class_m": ranges.class_bias(tuning.classes).tolist(),
                       "width_class_edges_fwhm": list(WIDTH_EDGES), "grid": tuning.grid.to_dict("records")},
        "range_correction": corr.to_dict(),
        "cfd_check_before": cfd_check(dr[on_target]), "cfd_check_after": cfd_check(dr_after[on_target]),
        "cfd_check_all_after": cfd_check(dr_after),
        "system_waveform": Path(out_path).name,
    }
    if result["cfd_check_after"]["n"] and result["cfd_check_after"]["frac_within_0_10_m"] < 0.95:
        warnings.warn(f"dataset {name}: CFD vs DR ranges: only {result['cfd_check_after']['frac_within_0_10_m']:.1%} "
                      "within 0.10 m (the paper's criterion is > 95 %); consider tuning sensor.cfd", WaveforestWarning, stacklevel=2)
    system.meta.update({k: result[k] for k in ("noise_mean", "noise_sd", "n_pulses")})
    system.save(out_path)
    write_json(result, json_path)
    if plot_path is not None:

        plot_system_waveform(system, plot_path, title=f"S(t) of {name} ({pulses.target.size} pulses)",
                             tuning=tuning)
    return result


@click.command()
@dataset_pulses_options
@click.option("--out", "out", type=OUT_FILE, required=True, help="System waveform S(t) (Parquet: t_ns, s, s_sd).")
@click.option("--json", "json_out", type=OUT_FILE, required=True, help="Calibration JSON (noise, FWHM, counts, a, b, CFD check).")
@click.option("--plot", "plot", type=OUT_FILE, default=None, help="Optional PNG of S(t) with its spread.")
@click.option("--agc-fit", "agc_fit", type=EXISTING_FILE, default=None,
              help="The agc step's JSON (a, b, n0), if the table lacks them in its metadata.")
@stage_options
def calibrate(pulses, targets_csv, datasets_csv, out, json_out, plot, agc_fit, cfg):
    """System waveform S(t) and noise of one dataset from reference targets (Eq. 8, docs/method.md §(e)).

    PULSES is the AGC-normalised pulse table of one dataset (`waveforest agc` output).
    """

    fit = json.loads(open(agc_fit).read()) if agc_fit else None
    res = run(pulses, read_targets(targets_csv), read_datasets(datasets_csv), out, json_out, cfg,
              plot_path=plot, agc_fit=fit)
    chk = res["cfd_check_after"]
    frac = "n/a" if chk["frac_within_0_10_m"] is None else f"{100 * chk['frac_within_0_10_m']:.1f} %"
    c = res["cfd"]
    how = "tuned" if res["cfd_tuning"]["tuned"] else "as configured"
    click.echo(f"calibrate: {res['dataset']}: S(t) FWHM {res['fwhm_ns']:.2f} ns from {res['n_pulses']} pulses, "
               f"noise {res['noise_mean']:.2f} +- {res['noise_sd']:.2f} DN, CFD f = {c['fraction']:.2f}, "
               f"delay {c['delay_ns']:.2f} ns ({how}), targets' |dR| < 0.10 m: {frac}; "
               f"wrote {out} and {json_out}" + (f" and {plot}" if plot else ""))
