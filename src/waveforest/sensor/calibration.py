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

Sensor effects of the simulation model (``simulate.effects``, src/waveforest/effects.py) that
also act on the targets' waveforms are inverted before Eq. 8, so that S(t) is the system
waveform of the model that will use it (:func:`linearise`): the detector saturation
``nonlinearity`` L (the signal model's ``V - c-bar = L tanh(v / L)``; each pulse at L / g, g its
AGC gain, as the saturation acts after the gain) and ``trigger_loss`` f
(the earliest fraction f of a target's near-delta sigma is lost, which scales its whole echo
by 1 - f). Without them a model with the effect would apply it twice: once through S(t), once
in the signal model. ``diagnose`` recalibrates in the same way for each value it tries
(:class:`CalibrationPulses`).

The same stage sets the CFD against the DR ranges (METHOD.md f) on the target pulses
(calibration and AGC targets) and ``calibrate.cfd_pulses`` pulses drawn at random from the
dataset (seeded), whose echoes span the widths of ground and vegetation: it tunes the CFD
fraction and delay (``calibrate.tune_cfd``; cfd_tuning.py), fits the amplitude-dependent range
correction dR(Apeak) on all of them (:func:`fit_range_correction`), and reports the paper's
check (the fraction with |dR| < 0.10 m and the bias) on the target pulses before and after the
correction. The JSON keeps the CFD with its correction (:func:`cfd_of`): every stage that
detects echoes with this calibration uses that pair.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..errors import WaveforestError, WaveforestWarning
from ..io.tables import iter_pulses, list_to_padded
from . import _checks
from .agc import GAIN_COLUMN, _single_dataset, read_agc_metadata, write_json
from .cfd import RangeCorrection
from .cfd_tuning import WIDTH_EDGES, tune_cfd
from .features import first_echo_features
from .noise import noise_stats
from .params import CFD_CHECK_M, FINE_NS, RANGE_GATE_M, CFDParams, FeatureParams
from .signal import saturation_levels
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


LINEARISE_MAX = 3.0
""":func:`linearise` caps the linearised signal at this many saturation levels L: beyond it
``tanh`` lies within 0.5 % of 1, and a recorded value there no longer tells the input."""


def linearise(v, nonlinearity=0.0, trigger_loss: float = 0.0) -> np.ndarray:
    """Planar-target signal above the noise mean with the sensor effects inverted, DN.

    ``L artanh(v / L) / (1 - f)``: the inverse of the signal model's saturation
    ``v -> L tanh(v / L)`` (L = ``nonlinearity``, a scalar or an array broadcast against ``v``,
    e.g. one level per pulse as a column; 0 = linear; capped at ``LINEARISE_MAX`` L) and of the
    loss of the earliest fraction f = ``trigger_loss`` of a near-delta sigma (the echo scaled
    by 1 - f). NaN stays NaN.
    """
    v = np.asarray(v, dtype=np.float64)
    level = np.asarray(nonlinearity, dtype=np.float64)
    if not np.all(level >= 0):
        raise ValueError(f"nonlinearity (saturation level, DN) must be >= 0, got {nonlinearity}")
    if not 0.0 <= trigger_loss < 1.0:
        raise ValueError(f"trigger_loss must be in [0, 1), got {trigger_loss}")
    if np.any(level > 0):
        lim = math.tanh(LINEARISE_MAX)
        safe = np.where(level > 0, level, 1.0)
        v = np.where(level > 0, safe * np.arctanh(np.clip(v / safe, -lim, lim)), v)
    return v / (1.0 - trigger_loss) if trigger_loss else v


def calibrate_system_waveform(samples, lengths, sampling_ns, echo_time_ns, range_m, sigma, noise_mean, *,
                              window_ns=(-20.0, 60.0), nonlinearity=0.0,
                              trigger_loss: float = 0.0) -> SystemWaveform:
    """S(t) by Eq. 8 averaged over planar-target pulses (METHOD.md e).

    Parameters
    ----------
    samples : (n, n_s) DN, AGC-normalised waveforms.  lengths : (n,).
    sampling_ns : float or (n,), ns.  echo_time_ns : (n,) first DR echo, ns from the first sample.
    range_m : (n,) m.  sigma : (n,) target cross-section per unit power (HDRF/pi [x cos]).
    noise_mean : float, c-bar, DN.  window_ns : (lo, hi) time span of S(t) around the echo.
    nonlinearity, trigger_loss : sensor effects of the model, inverted on each pulse before
        Eq. 8 (:func:`linearise`); 0 = off; nonlinearity a scalar or (n,) levels per pulse, DN.

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
    level = _checks.per_pulse(nonlinearity, n, "nonlinearity", nonnegative=True)
    t = calibration_grid(window_ns)
    s1 = np.zeros(t.size)
    s2 = np.zeros(t.size)
    cnt = np.zeros(t.size)
    for start in range(0, n, _CHUNK):  # blocks of pulses, each vectorised
        sl = slice(start, start + _CHUNK)
        v = resample_aligned(x[sl], lens[sl], dt[sl], te[sl], t)
        si = linearise(v - noise_mean, level[sl, None], trigger_loss) * (r[sl] ** 2 / sg[sl])[:, None]
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
    meta = {"n_pulses": int(n)}
    if level.any() or trigger_loss:
        meta.update(nonlinearity=float(np.median(level)), trigger_loss=float(trigger_loss))
    return SystemWaveform(t, mean, sd, meta)


def cfd_check(dr_minus_cfd_m) -> dict:
    """The paper's CFD criterion on dR = DR range - CFD range, m (gated at RANGE_GATE_M)."""
    d = np.asarray(dr_minus_cfd_m, dtype=np.float64)
    d = d[np.isfinite(d) & (np.abs(d) < RANGE_GATE_M)]
    if d.size == 0:
        return {"n": 0, "frac_within_0_10_m": None, "bias_m": None, "sd_m": None}
    return {"n": int(d.size), "frac_within_0_10_m": float(np.mean(np.abs(d) < CFD_CHECK_M)),
            "bias_m": float(d.mean()), "sd_m": float(d.std(ddof=1)) if d.size > 1 else 0.0}


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


CALIBRATION_EFFECTS = ("nonlinearity", "trigger_loss")
"""Sensor effects that also shape the calibration targets' waveforms (:func:`linearise`)."""


def calibration_effects(effects: dict | None) -> dict:
    """The switched-on effects of ``effects`` that the calibration inverts (nonlinearity, trigger_loss)."""
    effects = effects or {}
    return {k: float(effects[k]) for k in CALIBRATION_EFFECTS if effects.get(k)}


def model_sensor_effects(cfg: dict) -> dict:
    """:func:`calibration_effects` of the simulation model (``simulate.effects``)."""
    return calibration_effects(cfg["simulate"]["effects"])


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

    # CFD (tuned) and range correction against the DR ranges (METHOD.md f)
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
        from .plots import plot_system_waveform

        plot_system_waveform(system, plot_path, title=f"S(t) of {name} ({pulses.target.size} pulses)",
                             tuning=tuning)
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


def cfd_of(calibration: dict) -> CFDParams | None:
    """The CFD a calibration JSON's range correction was fitted with (None if absent: older files)."""
    c = calibration.get("cfd")
    return CFDParams.from_dict(c) if c else None


def range_correction_of(calibration: dict) -> RangeCorrection:
    """The range correction stored in a calibration JSON (identity if absent)."""
    return RangeCorrection.from_dict(calibration.get("range_correction"))
