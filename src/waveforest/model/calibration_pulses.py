"""The calibration-target pulses of one dataset that Eq. 8 averages (docs/method.md §(e)).

:func:`read_calibration_pulses` gathers them from an AGC-normalised pulse table (the ``agc``
output): the pulses on calibration targets of the dataset's year that are usable (a first DR
echo, a finite range, incidence zenith within ``max_zenith_deg``, peak below the digitiser
maximum), their noise and their sigma = HDRF / pi (times |cos(incidence)| if
``cos_incidence``). :meth:`CalibrationPulses.system_waveform` turns them into S(t) under a
model's sensor effects; ``calibrate`` does so once, ``diagnose`` for each value it tries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.errors import WaveforestError
from waveforest.io.pulses import iter_pulses, list_to_padded, single_dataset
from waveforest.io.results import read_agc_metadata
from waveforest.io.tables import dataset_year
from waveforest.rng import named_generator
from waveforest.sensor.agc import GAIN_COLUMN
from waveforest.sensor.calibration import calibrate_system_waveform
from waveforest.sensor.noise import noise_stats
from waveforest.sensor.signal import saturation_levels
from waveforest.sensor.system_waveform import SystemWaveform
from waveforest.sensor.targets import pulse_targets

COLUMNS = ["dataset", "dir_z", "range_m", "sampling_ns", "samples", "echo_x", "echo_y", "echo_time_ns"]
"""Pulse-table columns read (with the AGC gain column when the table has it)."""


@dataclass(frozen=True)
class TargetPulseSettings:
    """What selects and weighs the calibration-target pulses (config section ``calibrate``).

    noise_tail : last samples of a pulse that give the noise.  window_ns : (start, end) of
    S(t), ns from the first DR echo.  max_zenith_deg : largest incidence zenith, degrees.
    cos_incidence : sigma times |cos(incidence)|.  min_pulses : fewest usable pulses.
    digitizer_max : clipping level, DN (``sensor.digitizer_max``).  seed : study seed (the
    random extra pulses).
    """

    noise_tail: int
    window_ns: tuple
    max_zenith_deg: float
    cos_incidence: bool
    min_pulses: int
    digitizer_max: float
    seed: int


def gather_target_pulses(path: Path, targets, datasets, batch_rows: int, progress: bool, extra: int = 0,
                         seed: int = 0):
    """Target pulses of a one-dataset pulse table, and ``extra`` others drawn at random (seeded).

    Returns (dataset, year, dict of arrays or None); ``target`` is -1 for a pulse off the targets.
    """
    from tqdm import tqdm

    names: set = set()
    keep = []
    year = None
    has_gain = GAIN_COLUMN in pq.read_schema(path).names
    cols = COLUMNS + ([GAIN_COLUMN] if has_gain else [])
    n_rows = pq.read_metadata(path).num_rows
    rng = named_generator("calibrate_extra", int(seed))
    drawn = np.zeros(n_rows, dtype=bool)
    drawn[rng.choice(n_rows, size=min(int(extra), n_rows), replace=False)] = True
    start = 0
    for batch in tqdm(iter_pulses(path, batch_rows, columns=cols), desc="calibrate: read", unit="batch",
                      disable=not progress):
        names.update(set(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str))))
        name = single_dataset(names, path)
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
    name = single_dataset(names, path)
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


def calibration_target_pulses(pulses_path: Path, targets, datasets, settings: TargetPulseSettings, agc_fit,
                              batch_rows: int, progress: bool, extra: int = 0):
    """The target pulses of a pulse table and ``extra`` random others.

    Returns (CalibrationPulses, dict of arrays of all pulses read, AGC metadata, usable mask:
    a first DR echo and a range, not clipped, and on a target within the zenith limit or off the
    targets).
    """
    if not pulses_path.exists():
        raise WaveforestError(f"{pulses_path}: no such file")
    s = settings
    meta = read_agc_metadata(pulses_path)
    if agc_fit:
        meta = {**meta, **{k: agc_fit[k] for k in ("a", "b", "n0") if k in agc_fit}}
    name, year, d = gather_target_pulses(pulses_path, targets, datasets, batch_rows, progress, extra, s.seed)
    if d is None:
        raise WaveforestError(f"{pulses_path}: no pulse of dataset {name} hits a target of year {year} in targets.csv")
    n0 = float(meta["n0"]) if meta.get("n0") is not None else None
    on_target = d["target"] >= 0
    is_cal = on_target & targets["calibration"].to_numpy(dtype=bool)[d["target"]]
    hdrf = np.where(on_target, targets["hdrf"].to_numpy(np.float64)[d["target"]], np.nan)
    cos_t = np.clip(-d["dir_z"], -1.0, 1.0)
    zen_ok = np.degrees(np.arccos(np.abs(cos_t))) <= s.max_zenith_deg + 1e-9
    raw_peak = np.nanmax(np.where(np.arange(d["samples"].shape[1])[None, :] < d["lengths"][:, None],
                                  d["samples"], -np.inf), axis=1).astype(np.float64)
    if n0 is not None:
        raw_peak = (raw_peak - n0) * d["gain"] + n0
    not_sat = raw_peak < s.digitizer_max - 0.5
    usable = np.isfinite(d["t_echo"]) & np.isfinite(d["range_m"]) & (d["range_m"] > 0) & (d["lengths"] >= 2)
    cal = is_cal & (hdrf > 0) & zen_ok & not_sat & usable
    if cal.sum() < s.min_pulses:
        raise WaveforestError(
            f"dataset {name}: {int(cal.sum())} usable pulse(s) on calibration targets (targets.csv rows with "
            f"calibration = 1 and year {year}; usable = a first DR echo, a finite range_m (sensor position known), "
            f"incidence zenith <= calibrate.max_zenith_deg, peak below the digitiser maximum); at least "
            f"calibrate.min_pulses = {s.min_pulses} are needed")
    idx = np.flatnonzero(cal)
    if n0 is not None:
        noise = noise_stats(d["samples"][idx], d["lengths"][idx], s.noise_tail, gain=d["gain"][idx], n0=n0)
    else:
        noise = noise_stats(d["samples"][idx], d["lengths"][idx], s.noise_tail)
    sigma = hdrf[idx] / math.pi * (np.abs(cos_t[idx]) if s.cos_incidence else 1.0)
    pulses = CalibrationPulses(str(name), int(year), d["samples"][idx], d["lengths"][idx], d["sampling_ns"][idx],
                               d["t_echo"][idx], d["range_m"][idx], sigma, d["target"][idx], d["gain"][idx], noise,
                               s.window_ns)
    return pulses, d, meta, usable & not_sat & (zen_ok | ~on_target)


def read_calibration_pulses(pulses_path, targets, datasets, settings: TargetPulseSettings, *,
                            agc_fit: dict | None = None, batch_rows: int = 65536,
                            progress: bool = False) -> CalibrationPulses:
    """The calibration-target pulses of an AGC-normalised pulse table (the ``agc`` output).

    ``targets``, ``datasets``: DataFrames of targets.csv and datasets.csv; ``agc_fit``: the
    ``agc`` JSON (a, b, n0) when the table's metadata lacks them. Raises WaveforestError if too
    few pulses hit calibration targets.
    """
    return calibration_target_pulses(Path(pulses_path), targets, datasets, settings, agc_fit, batch_rows,
                                     progress)[0]
