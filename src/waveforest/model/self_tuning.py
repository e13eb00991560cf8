"""Noise, system pulse width, CFD and range correction of one pulse table from its own DR echoes,
and the paper's CFD-DR check on every pulse (docs/own-data.md).

Two passes over the table, so that memory stays bounded whatever its size: the first draws
``tuning_pulses`` pulses at random (seeded) for the noise, the width and the grid search
(:mod:`waveforest.sensor.self_calibration`, :func:`waveforest.sensor.cfd_tuning.tune_cfd`); the
second runs the chosen CFD on every pulse and keeps four numbers per pulse for the check and the
plot.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.errors import WaveforestError
from waveforest.io.pulses import PULSE_SCHEMA, TableError, iter_pulses, list_to_padded
from waveforest.rng import named_generator
from waveforest.sensor.cfd import RangeCorrection, detect_echoes
from waveforest.sensor.cfd_tuning import WIDTH_EDGES, CFDTuning, tune_cfd
from waveforest.sensor.features import first_echo_features
from waveforest.sensor.noise import NoiseStats
from waveforest.sensor.params import CFDParams, FeatureParams
from waveforest.sensor.self_calibration import (
    closing_note,
    dr_agreement,
    dr_minus_cfd,
    dr_visible,
    flat_top,
    single_echo_mask,
    system_fwhm,
    tail_noise,
)

STREAM_ROWS = 8192
"""Pulses per batch read: a batch of 256-sample waveforms, padded, with the CFD and features on
it, takes ~100 MB, which keeps a whole run within the ingest memory bound (docs/own-data.md)."""

COLUMNS = ["dataset", "sampling_ns", "samples", "n_echoes", "echo_time_ns"]
"""Pulse-table columns the tuning reads."""

LOW_SNR = 5.0
"""If fewer than 20 single echoes reach ``min_snr``, the width estimate takes those above this
many noise SDs (and says so)."""


@dataclass(frozen=True)
class SelfTuningSettings:
    """Settings of :func:`tune_pulse_table` (config sections ``tune_cfd``, ``calibrate``, ``sensor``).

    tuning_pulses : pulses drawn (seeded by ``seed``) for the noise, the width and the grid.
    noise_tail : last samples per pulse for the noise.  noise_guard_ns : ns after the last DR
    echo left out.  noise_clip_sd : noise SDs beyond which tail samples are left out.
    min_snr : noise SDs a single echo peaks above for the system width.  tune : False keeps
    ``cfd``'s pair.  range_correction_bins, range_correction_min_pulses : range-correction fit.
    cfd : the starting CFD.  features : first-echo feature settings.
    """

    seed: int
    tuning_pulses: int
    noise_tail: int
    noise_guard_ns: float
    noise_clip_sd: float
    min_snr: float
    tune: bool
    range_correction_bins: int
    range_correction_min_pulses: int
    cfd: CFDParams
    features: FeatureParams


@dataclass(frozen=True)
class Pulses:
    """Arrays of a batch of pulses: padded samples (n, n_s) DN, lengths, sampling_ns, first and
    last DR echo time (ns, NaN without), number of DR echoes."""

    samples: np.ndarray
    lengths: np.ndarray
    sampling_ns: np.ndarray
    dr_time_ns: np.ndarray
    last_echo_ns: np.ndarray
    n_dr: np.ndarray

    @classmethod
    def of(cls, table: pa.Table) -> Pulses:
        x, lens = list_to_padded(table.column("samples"))
        te, tl = list_to_padded(table.column("echo_time_ns"), dtype=np.float64)
        n = table.num_rows
        first = np.full(n, np.nan)
        last = np.full(n, np.nan)
        if te.shape[1]:
            has = tl > 0
            first[has] = te[has, 0]
            last[has] = te[np.flatnonzero(has), tl[has] - 1]
        dt = table.column("sampling_ns").to_numpy(zero_copy_only=False).astype(np.float64)
        return cls(x, lens, dt, first, last, tl)

    def take(self, idx) -> Pulses:
        return Pulses(*(a[idx] for a in (self.samples, self.lengths, self.sampling_ns, self.dr_time_ns,
                                          self.last_echo_ns, self.n_dr)))


@dataclass(frozen=True)
class SelfTuning:
    """What :func:`tune_pulse_table` found.

    ``result``: the JSON content (a calibration JSON without S(t): dataset, noise_mean,
    noise_sd, fwhm_ns, cfd, range_correction, and the check). The per-pulse arrays (n,) of the
    check, for the residual plot: CFD echo amplitude, DN; first-echo FWHM / system FWHM;
    residual (DR - corrected CFD range), m; ``plotted`` the pulses with a DR echo and a CFD echo.
    """

    result: dict
    amplitude: np.ndarray
    width_rel: np.ndarray
    residual_m: np.ndarray
    plotted: np.ndarray
    correction: RangeCorrection

    def plot_title(self) -> str:
        """The residual plot's title."""
        r = self.result
        return (f"{r['dataset']}: CFD vs DR, {percent(r['within_0_10_m'])} within 0.10 m "
                f"({r['n_pulses']:,} pulses with a DR echo)")


@dataclass(frozen=True)
class _SampleTuning:
    """The first pass: the dataset, the noise, the system width and the CFD tuned on the sample."""

    dataset: str
    noise: NoiseStats
    fwhm_ns: float
    width_report: dict
    tuning: CFDTuning
    n_tuned: int


def percent(v) -> str:
    """A share as ``12.3 %`` (``n/a`` for None)."""
    return "n/a" if v is None else f"{100 * v:.1f} %"


def check_columns(path: Path) -> int:
    """Rows of the pulse table at ``path``; raises WaveforestError without the columns read here."""
    if not path.exists():
        raise WaveforestError(f"{path}: no such file")
    try:
        schema = pq.read_schema(path)
        n = pq.read_metadata(path).num_rows
    except (pa.ArrowInvalid, OSError) as exc:
        raise TableError(f"{path}: not a readable Parquet file ({exc})") from exc
    missing = [c for c in COLUMNS if c not in schema.names]
    if missing:
        raise TableError(f"{path}: pulse table lacks column(s) {', '.join(missing)} (the output of `waveforest ingest` "
                         f"has {', '.join(PULSE_SCHEMA.names)})")
    if n == 0:
        raise WaveforestError(f"{path}: the pulse table is empty")
    return n


def _tuning_pulses(path: Path, n_rows: int, k: int, seed: int, batch_rows: int, bar) -> tuple[str, Pulses]:
    """The dataset name and ``k`` pulses drawn at random (seeded) from the table."""
    rng = named_generator("tune_cfd_pulses", int(seed))
    drawn = np.zeros(n_rows, dtype=bool)
    drawn[rng.choice(n_rows, size=min(int(k), n_rows), replace=False)] = True
    names: set[str] = set()
    parts, start = [], 0
    for batch in iter_pulses(path, batch_rows, columns=COLUMNS):
        names.update(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str)).tolist())
        if len(names) > 1:
            raise WaveforestError(f"{path}: the pulse table holds several datasets ({', '.join(sorted(names))}); "
                                  "tune-cfd takes one file's pulses")
        on = np.flatnonzero(drawn[start:start + batch.num_rows])
        start += batch.num_rows
        if on.size:
            parts.append(batch.take(pa.array(on)))
        bar.update(batch.num_rows)
    return names.pop(), Pulses.of(pa.concat_tables(parts))


def _first_echo_widths(p: Pulses, noise: NoiseStats, fp: FeatureParams) -> dict:
    """First-echo features of ``p`` at the DR time (NaN without a DR echo)."""
    return first_echo_features(p.samples, p.lengths, p.sampling_ns, p.dr_time_ns, noise.mean, noise.sd,
                               fp.segment_sd, fp.peak_rise_sd, echo_search_ns=fp.echo_search_ns)


def _system_width(p: Pulses, noise: NoiseStats, fp: FeatureParams, min_snr: float) -> tuple[float, dict, dict]:
    """System FWHM from the strong single echoes of ``p``, the width report, and the features at the DR time."""
    feats = _first_echo_widths(p, noise, fp)
    flat = flat_top(p.samples, p.lengths)
    snr = min_snr
    mask = single_echo_mask(feats["FWHM"], feats["Apeak"], feats["Npeaks"], p.n_dr, flat, noise.sd, snr)
    est = system_fwhm(feats["FWHM"][mask])
    if not np.isfinite(est.fwhm_ns) and min_snr > LOW_SNR:
        snr = LOW_SNR
        mask = single_echo_mask(feats["FWHM"], feats["Apeak"], feats["Npeaks"], p.n_dr, flat, noise.sd, snr)
        est = system_fwhm(feats["FWHM"][mask])
    if not np.isfinite(est.fwhm_ns):
        raise WaveforestError(
            f"only {est.n_echoes} single echoes (one DR echo, one peak, not clipped, peak >= {snr:g} noise SDs) among "
            f"{len(p.lengths)} pulses: too few to estimate the system pulse width")
    report = {"system_fwhm_ns": est.fwhm_ns, "n_single_echoes": est.n_echoes, "single_echo_fwhm_spread_ns": est.spread_ns,
              "min_snr": snr, "n_clipped": int(flat.sum())}
    return est.fwhm_ns, report, feats


def _tune_on_sample(path: Path, n_rows: int, s: SelfTuningSettings, batch_rows: int, bar) -> _SampleTuning:
    """Pass 1: draw the tuning pulses; noise from their tails, the system width, the CFD grid search."""
    name, sub = _tuning_pulses(path, n_rows, s.tuning_pulses, s.seed, batch_rows, bar)
    try:
        noise = tail_noise(sub.samples, sub.lengths, sub.sampling_ns, sub.last_echo_ns, tail=s.noise_tail,
                           guard_ns=s.noise_guard_ns, clip_sd=s.noise_clip_sd)
    except ValueError as exc:
        raise WaveforestError(f"{path}: {exc}") from None
    fwhm, width_report, feats = _system_width(sub, noise, s.features, s.min_snr)
    has = np.isfinite(sub.dr_time_ns)
    if has.sum() < 2:
        raise WaveforestError(f"{path}: {int(has.sum())} of {len(has)} pulses drawn have a DR echo; the CFD is tuned "
                              "against DR echoes")
    d = np.flatnonzero(has)
    t = sub.take(d)
    tuning = tune_cfd(t.samples, t.lengths, t.sampling_ns, t.dr_time_ns, feats["FWHM"][d], noise.mean, noise.sd,
                      s.cfd, fwhm, tune=s.tune, n_bins=s.range_correction_bins,
                      min_per_bin=s.range_correction_min_pulses)
    return _SampleTuning(name, noise, fwhm, width_report, tuning, int(len(d)))


def _check_every_pulse(path: Path, first: _SampleTuning, fp: FeatureParams, batch_rows: int, bar) -> dict:
    """Pass 2: the chosen CFD on every pulse; per pulse DR - CFD and the residual (m), amplitude,
    first-echo FWHM at the DR time, DR echo present and visible, sampling interval."""
    noise, cfd, corr = first.noise, first.tuning.cfd, first.tuning.ranges.correction
    level = noise.mean + cfd.arming_sd * noise.sd
    cols = {k: [] for k in ("dr", "res", "amp", "width", "has", "vis", "dt")}
    for batch in iter_pulses(path, batch_rows, columns=COLUMNS):
        p = Pulses.of(batch)
        ech = detect_echoes(p.samples, p.lengths, p.sampling_ns, noise.mean, noise.sd, cfd, 1)
        dr = dr_minus_cfd(p.dr_time_ns, ech.times_ns[:, 0])
        amp = ech.amplitudes[:, 0]
        w = _first_echo_widths(p, noise, fp)["FWHM"]
        cols["dr"].append(dr.astype(np.float32))
        cols["res"].append((dr - corr(amp)).astype(np.float32))
        cols["amp"].append(amp.astype(np.float32))
        cols["width"].append(w.astype(np.float32))
        cols["has"].append(np.isfinite(p.dr_time_ns))
        cols["vis"].append(dr_visible(p.samples, p.lengths, p.sampling_ns, p.dr_time_ns, level, first.fwhm_ns / 2))
        cols["dt"].append(p.sampling_ns.astype(np.float32))
        bar.update(batch.num_rows)
    return {k: np.concatenate(v) for k, v in cols.items()}


def _result(path: Path, n_rows: int, s: SelfTuningSettings, first: _SampleTuning, a: dict) -> dict:
    """The JSON content: noise, width, CFD, range correction, the check and the tuning grid."""
    noise, tuning, fwhm = first.noise, first.tuning, first.fwhm_ns
    cfd, corr = tuning.cfd, tuning.ranges.correction
    agree = dr_agreement(a["dr"], a["res"], a["has"], a["vis"])
    sampling = float(np.median(a["dt"]))
    result = {
        "dataset": first.dataset, "source": str(path), "n_pulses_total": int(n_rows), "n_pulses": agree["n_pulses"],
        "noise_mean": noise.mean, "noise_sd": noise.sd, "noise_sd_analog": noise.sd_analog, "noise_lag1": noise.lag1,
        "noise_quantised": noise.quantised, "noise_n_samples": noise.n_samples, "noise_n_pulses": noise.n_pulses,
        "noise_tail": s.noise_tail, "noise_guard_ns": s.noise_guard_ns,
        "system_fwhm_ns": fwhm, "fwhm_ns": fwhm, **{k: v for k, v in first.width_report.items() if k != "system_fwhm_ns"},
        "sampling_ns": sampling,
        "fraction": cfd.fraction, "delay_ns": cfd.delay_ns, "cfd": cfd.to_dict(),
        "range_correction": corr.to_dict(),
        **{k: v for k, v in agree.items() if k != "n_pulses"},
        "criterion": "share of pulses with a DR echo whose first CFD echo, range-corrected, lies within 0.10 m of the "
                     "first DR echo (paper: > 95 %, no bias); counted over all of them, gated share beside it",
        "cfd_tuning": {"tuned": tuning.tuned, "reason": tuning.reason, "n_pulses": first.n_tuned,
                       "bias_per_width_class_m": tuning.ranges.class_bias(tuning.classes).tolist(),
                       "width_class_edges_fwhm": list(WIDTH_EDGES), "grid": tuning.grid.to_dict("records")},
    }
    result["note"] = closing_note(agree, sampling, cfd.arming_sd)
    return result


def tune_pulse_table(pulses_path, settings: SelfTuningSettings, *, batch_rows: int = STREAM_ROWS,
                     progress: bool = True) -> SelfTuning:
    """Tune the CFD of one pulse table (one dataset, raw DN; the ``ingest`` output) on its own DR echoes.

    Raises WaveforestError for a missing, empty or multi-dataset table, too few single echoes
    for the system width, or fewer than two drawn pulses with a DR echo.
    """
    from tqdm import tqdm

    path = Path(pulses_path)
    n_rows = check_columns(path)
    with tqdm(total=n_rows, unit="pulse", unit_scale=True, disable=not progress, file=sys.stderr,
              desc=f"tune-cfd {path.name}, pass 1/2 (sample and tune)") as bar:
        first = _tune_on_sample(path, n_rows, settings, batch_rows, bar)
        bar.reset(total=n_rows)
        bar.set_description(f"tune-cfd {path.name}, pass 2/2 (check every pulse)")
        a = _check_every_pulse(path, first, settings.features, batch_rows, bar)
    corr = first.tuning.ranges.correction
    return SelfTuning(_result(path, n_rows, settings, first, a), a["amp"], a["width"] / first.fwhm_ns, a["res"],
                      a["has"] & np.isfinite(a["dr"]), corr)


def summary_line(res: dict, out) -> str:
    """The one-line CLI summary of a tuning result (:attr:`SelfTuning.result`) written to ``out``."""
    med = res["median_residual_m"]
    return (f"tune-cfd: {res['dataset']}: noise {res['noise_mean']:.2f} +- {res['noise_sd']:.2f} DN, system FWHM "
            f"{res['system_fwhm_ns']:.2f} ns, CFD f = {res['fraction']:.2f}, delay {res['delay_ns']:.2f} ns "
            f"({'tuned' if res['cfd_tuning']['tuned'] else 'as configured'}); within 0.10 m of the DR echo: "
            f"{percent(res['within_0_10_m'])} of {res['n_pulses']:,} pulses (gated {percent(res['within_0_10_m_gated'])}), "
            f"median residual {'n/a' if med is None else f'{100 * med:.1f} cm'}; wrote {out}")
