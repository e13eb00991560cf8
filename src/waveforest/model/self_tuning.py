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
from waveforest.sensor.params import RANGE_GATE_M, CFDParams, FeatureParams
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

PLOT_SAMPLE = 20_000
"""Pulses kept for the residual plot (a seeded reservoir sample beyond that, so memory stays bounded)."""

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
    noise_sd, fwhm_ns, cfd, range_correction, and the check). For the residual plot, arrays (n,)
    over the pulses with a DR echo and a CFD echo, all of them in table order up to
    :data:`PLOT_SAMPLE`, else a seeded reservoir sample of that many: CFD echo amplitude, DN;
    first-echo FWHM / system FWHM; residual (DR - corrected CFD range), m; ``plotted`` (all True).
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


def _check_every_pulse(path: Path, n_rows: int, first: _SampleTuning, fp: FeatureParams, batch_rows: int,
                       seed: int, bar) -> dict:
    """Pass 2: the chosen CFD on every pulse. Returns the agreement (:func:`_agreement`), the median
    sampling interval and, for the plot, a seeded sample (:func:`_keep_sample`) of at most
    :data:`PLOT_SAMPLE` of the pulses with a DR and a CFD echo: float32 CFD amplitude, first-echo
    FWHM at the DR time and residual (DR - corrected CFD range, m). Held per pulse: the gated
    residuals (4 bytes each, 8 at the end); the rest is counted batch by batch."""
    noise, cfd, corr = first.noise, first.tuning.cfd, first.tuning.ranges.correction
    level = noise.mean + cfd.arming_sd * noise.sd
    r = np.empty(n_rows, np.float32)
    sample = {k: np.empty(PLOT_SAMPLE, np.float32) for k in ("amp", "width", "res")}
    rng = named_generator("quicklook_scatter", int(seed))
    parts, dt_counts, n_gated, n_seen = [], {}, 0, 0
    for batch in iter_pulses(path, batch_rows, columns=COLUMNS):
        p = Pulses.of(batch)
        ech = detect_echoes(p.samples, p.lengths, p.sampling_ns, noise.mean, noise.sd, cfd, 1)
        dr = dr_minus_cfd(p.dr_time_ns, ech.times_ns[:, 0]).astype(np.float32)
        amp = ech.amplitudes[:, 0]
        res = (dr_minus_cfd(p.dr_time_ns, ech.times_ns[:, 0]) - corr(amp)).astype(np.float32)
        has = np.isfinite(p.dr_time_ns)
        plotted = has & np.isfinite(dr)
        gated = plotted & (np.abs(dr.astype(np.float64)) < RANGE_GATE_M)
        r[n_gated:n_gated + int(gated.sum())] = res[gated]
        n_gated += int(gated.sum())
        width = _first_echo_widths(p, noise, fp)["FWHM"]
        n_seen = _keep_sample(sample, n_seen, {"amp": amp[plotted], "width": width[plotted], "res": res[plotted]}, rng)
        vis = dr_visible(p.samples, p.lengths, p.sampling_ns, p.dr_time_ns, level, first.fwhm_ns / 2)
        parts.append(dr_agreement(dr, res, has, vis))
        for v, c in zip(*np.unique(p.sampling_ns.astype(np.float32), return_counts=True)):
            dt_counts[v] = dt_counts.get(v, 0) + int(c)
        bar.update(batch.num_rows)
    out = {k: v[:min(n_seen, PLOT_SAMPLE)].copy() for k, v in sample.items()}
    r64 = r[:n_gated].astype(np.float64)
    del r
    out["agree"] = _agreement(parts, r64)
    out["sampling"] = _median_of_counts(dt_counts)
    return out


def _keep_sample(sample: dict, n_seen: int, new: dict, rng: np.random.Generator) -> int:
    """Reservoir sampling (Algorithm R) of the rows of ``new`` into the arrays of ``sample`` (length
    k) after ``n_seen`` rows; returns the rows seen. Keeps every row, in order, while at most k are seen."""
    k = len(next(iter(sample.values())))
    m = len(next(iter(new.values())))
    idx = np.arange(n_seen, n_seen + m)
    slot = idx.copy()
    late = idx >= k
    if late.any():
        slot[late] = np.floor(rng.random(int(late.sum())) * (idx[late] + 1)).astype(np.int64)
    put = slot < k  # later rows overwrite earlier ones in the same slot, as one by one
    for name, values in new.items():
        sample[name][slot[put]] = values[put]
    return n_seen + m


def _median_of_counts(counts: dict) -> float:
    """``float(np.median(x))`` of the float32 values ``x`` given as {value: count}."""
    values = np.array(sorted(counts), dtype=np.float32)
    cum = np.cumsum([counts[v] for v in values])
    n = int(cum[-1])
    lo, hi = (values[np.searchsorted(cum, k, side="right")] for k in ((n - 1) // 2, n // 2))
    return float(np.mean(np.array([lo, hi], dtype=np.float32)))


def _residual_stats(r: np.ndarray) -> tuple[float | None, float | None, float | None]:
    """Median, mean and robust SD (1.4826 MAD) of the gated residuals ``r`` (float64, consumed:
    sorted and overwritten in place), equal to those of :func:`dr_agreement` without its copies."""
    if not r.size:
        return None, None, None
    mean = float(np.mean(r))
    med = _median_in_place(r)
    np.subtract(r, med, out=r)
    np.abs(r, out=r)
    return float(med), mean, float(1.4826 * _median_in_place(r))


def _median_in_place(x: np.ndarray) -> np.float64:
    """``np.median(x)`` of a float64 array without NaN, partitioning ``x`` in place."""
    n = x.size
    k = (n - 1) // 2, n // 2
    x.partition(k)
    return np.mean(x[[k[0], k[1]]]) if n % 2 == 0 else x[k[0]]


def _agreement(parts: list[dict], r: np.ndarray) -> dict:
    """:func:`dr_agreement` of all pulses from its results per batch (``parts``, counts added) and
    the gated residuals of all pulses in table order (``r``, consumed)."""
    count = lambda share, n: 0 if share is None else round(share * n)  # noqa: E731
    n = sum(q["n_pulses"] for q in parts)
    n_gated = sum(q["n_gated"] for q in parts)
    within = sum(count(q["within_0_10_m"], q["n_pulses"]) for q in parts)
    below = sum(q["n_dr_below_noise"] for q in parts)
    within_vis = sum(count(q["within_0_10_m_dr_above_noise"], q["n_pulses"] - q["n_dr_below_noise"]) for q in parts)
    reasons = {k: sum(q["limits"][k]["n"] for q in parts) for k in parts[0]["limits"]} if parts else {}
    share = (lambda m: float(np.int64(m) / n)) if n else (lambda m: None)
    med, mean, sd = _residual_stats(r)
    return {
        "n_pulses": n,
        "within_0_10_m": share(within),
        "n_gated": n_gated,
        "within_0_10_m_gated": float(np.int64(within) / n_gated) if n_gated else None,
        "median_residual_m": med,
        "mean_residual_m": mean,
        "residual_sd_robust_m": sd,
        "limits": {k: {"n": m, "share": share(m)} for k, m in reasons.items()},
        "n_dr_below_noise": below,
        "within_0_10_m_dr_above_noise": float(np.int64(within_vis) / (n - below)) if n - below else None,
    }


def _result(path: Path, n_rows: int, s: SelfTuningSettings, first: _SampleTuning, a: dict) -> dict:
    """The JSON content: noise, width, CFD, range correction, the check and the tuning grid."""
    noise, tuning, fwhm = first.noise, first.tuning, first.fwhm_ns
    cfd, corr = tuning.cfd, tuning.ranges.correction
    agree, sampling = a["agree"], a["sampling"]
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
    with tqdm(total=n_rows, unit="waveform", unit_scale=True, disable=not progress, file=sys.stderr,
              desc=f"tune-cfd {path.name}, pass 1/2 (sample and tune)") as bar:
        first = _tune_on_sample(path, n_rows, settings, batch_rows, bar)
        bar.reset(total=n_rows)
        bar.set_description(f"tune-cfd {path.name}, pass 2/2 (check every pulse)")
        a = _check_every_pulse(path, n_rows, first, settings.features, batch_rows, settings.seed, bar)
    corr = first.tuning.ranges.correction
    return SelfTuning(_result(path, n_rows, settings, first, a), a["amp"], a["width"] / first.fwhm_ns, a["res"],
                      np.ones(len(a["res"]), bool), corr)


def summary_line(res: dict, out) -> str:
    """The one-line CLI summary of a tuning result (:attr:`SelfTuning.result`) written to ``out``."""
    med = res["median_residual_m"]
    return (f"tune-cfd: {res['dataset']}: noise {res['noise_mean']:.2f} +- {res['noise_sd']:.2f} DN, system FWHM "
            f"{res['system_fwhm_ns']:.2f} ns, CFD f = {res['fraction']:.2f}, delay {res['delay_ns']:.2f} ns "
            f"({'tuned' if res['cfd_tuning']['tuned'] else 'as configured'}); within 0.10 m of the DR echo: "
            f"{percent(res['within_0_10_m'])} of {res['n_pulses']:,} pulses (gated {percent(res['within_0_10_m_gated'])}), "
            f"median residual {'n/a' if med is None else f'{100 * med:.1f} cm'}; wrote {out}")
