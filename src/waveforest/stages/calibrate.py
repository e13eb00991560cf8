"""The ``calibrate`` stage."""

from __future__ import annotations

import warnings
from pathlib import Path

import click
import numpy as np

from waveforest.cliutil import EXISTING_FILE, dataset_fit_options, stage_options
from waveforest.errors import WaveforestError, WaveforestWarning
from waveforest.io.results import read_agc_fit, write_calibration_json
from waveforest.io.tables import read_datasets, read_targets
from waveforest.model.calibration_pulses import calibration_target_pulses
from waveforest.report.plots import plot_system_waveform
from waveforest.sensor import checks
from waveforest.sensor.calibration import cfd_check
from waveforest.sensor.cfd_tuning import WIDTH_EDGES, tune_cfd
from waveforest.sensor.features import first_echo_features
from waveforest.settings import cfd_params, feature_params, model_sensor_effects, target_pulse_settings


def _cfd_against_dr(d: dict, checkable, noise, system_fwhm_ns: float, cfg: dict):
    """The CFD (tuned unless ``calibrate.tune_cfd`` is false) on the checkable pulses of ``d``.

    Returns (CFDTuning, on-target mask over those pulses).
    """
    sec = cfg["calibrate"]
    idx = np.flatnonzero(checkable)
    x, lens, dt, te = d["samples"][idx], d["lengths"][idx], d["sampling_ns"][idx], d["t_echo"][idx]
    fp = feature_params(cfg)
    width = first_echo_features(x, lens, dt, te, noise.mean, noise.sd, fp.segment_sd, fp.peak_rise_sd,
                                echo_search_ns=fp.echo_search_ns)["FWHM"]
    armed_sd = noise.sd / checks.gain_or_one(d["gain"][idx])  # the recorded noise, as the DR circuits see it
    tuning = tune_cfd(x, lens, dt, te, width, noise.mean, armed_sd, cfd_params(cfg), system_fwhm_ns,
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
    pulses, d, meta, checkable = calibration_target_pulses(Path(pulses_path), targets, datasets,
                                                           target_pulse_settings(cfg), agc_fit, batch_rows, progress,
                                                           extra=int(sec["cfd_pulses"]))
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
    write_calibration_json(result, json_path)
    if plot_path is not None:

        plot_system_waveform(system, plot_path, title=f"S(t) of {name} ({pulses.target.size} pulses)",
                             tuning=tuning)
    return result


@click.command()
@dataset_fit_options("System waveform S(t) (Parquet: t_ns, s, s_sd).",
                     ("--json", "json_out", "Calibration JSON (noise, FWHM, counts, a, b, CFD check)."),
                     "Optional PNG of S(t) with its spread.")
@click.option("--agc-fit", "agc_fit", type=EXISTING_FILE, default=None,
              help="The agc step's JSON (a, b, n0), if the table lacks them in its metadata.")
@stage_options
def calibrate(pulses, targets_csv, datasets_csv, out, json_out, plot, agc_fit, cfg):
    """System waveform S(t) and noise of one dataset from reference targets (Eq. 8, docs/method.md §(e)).

    PULSES is the AGC-normalised pulse table of one dataset (`waveforest agc` output).

    Example:

    \b
    waveforest calibrate agc.parquet --targets campaign/targets.csv --datasets campaign/datasets.csv --out system.parquet --json calibration.json
    """

    fit = read_agc_fit(agc_fit) if agc_fit else None
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
