"""The ``tune-cfd`` stage: noise, system pulse width, CFD and range correction of one pulse table
from its own DR echoes, and the paper's CFD-DR check on every pulse (docs/own-data.md).

Two passes over the table, so that memory stays bounded whatever its size: the first draws
``tune_cfd.tuning_pulses`` pulses at random (seeded) for the noise, the width and the grid
search (:mod:`waveforest.sensor.self_calibration`, :func:`waveforest.sensor.cfd_tuning.tune_cfd`);
the second runs the chosen CFD on every pulse and keeps four numbers per pulse for the check
and the plot.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.atomic import write_json
from waveforest.cliutil import EXISTING_FILE, OUT_FILE, stage_options, warnings_to_stderr
from waveforest.errors import WaveforestError
from waveforest.io.pulses import PULSE_SCHEMA, TableError, iter_pulses, list_to_padded
from waveforest.report.quicklook import plot_cfd_residuals
from waveforest.sensor.cfd import detect_echoes
from waveforest.sensor.cfd_tuning import WIDTH_EDGES, tune_cfd
from waveforest.sensor.features import first_echo_features
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
"""Pulse-table columns the stage reads."""

LOW_SNR = 5.0
"""If fewer than 20 single echoes reach ``tune_cfd.min_snr``, the width estimate takes those
above this many noise SDs (and says so)."""


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


def _check_columns(path: Path) -> int:
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
    rng = np.random.default_rng([int(seed), 0xCFD, 0x5E1F])
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


def _system_width(p: Pulses, noise, fp: FeatureParams, min_snr: float) -> tuple[float, dict, dict]:
    """System FWHM from the strong single echoes of ``p``, the width report, and the features at the DR time."""
    feats = first_echo_features(p.samples, p.lengths, p.sampling_ns, p.dr_time_ns, noise.mean, noise.sd,
                                fp.segment_sd, fp.peak_rise_sd, echo_search_ns=fp.echo_search_ns)
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


def run(pulses_path, json_path, cfg: dict, *, plot_path=None, batch_rows: int = STREAM_ROWS, progress: bool = True) -> dict:
    """Tune the CFD of one pulse table on its own DR echoes; write the JSON (and plot).

    Parameters
    ----------
    pulses_path : pulse table of one dataset (the ``ingest`` output; raw DN).
    json_path : output JSON; a calibration JSON without S(t) (dataset, noise_mean, noise_sd,
        fwhm_ns, cfd, range_correction), so ``features --cfd`` and ``features --calibration`` read it.
    cfg : validated config (sections tune_cfd, sensor, calibrate, seed).
    plot_path : optional PNG of the residuals against amplitude and echo width.

    Returns
    -------
    dict, the JSON content.
    """
    from tqdm import tqdm

    path = Path(pulses_path)
    sec = cfg["tune_cfd"]
    n_rows = _check_columns(path)
    fp = FeatureParams.from_config(cfg)
    with tqdm(total=2 * n_rows, unit="pulse", unit_scale=True, disable=not progress, file=sys.stderr,
              desc=f"tune-cfd {path.name}") as bar:
        name, sub = _tuning_pulses(path, n_rows, int(sec["tuning_pulses"]), int(cfg["seed"]), batch_rows, bar)
        try:
            noise = tail_noise(sub.samples, sub.lengths, sub.sampling_ns, sub.last_echo_ns, tail=int(sec["noise_tail"]),
                               guard_ns=float(sec["noise_guard_ns"]), clip_sd=float(sec["noise_clip_sd"]))
        except ValueError as exc:
            raise WaveforestError(f"{path}: {exc}") from None
        fwhm, width_report, feats = _system_width(sub, noise, fp, float(sec["min_snr"]))
        has = np.isfinite(sub.dr_time_ns)
        if has.sum() < 2:
            raise WaveforestError(f"{path}: {int(has.sum())} of {len(has)} pulses drawn have a DR echo; the CFD is tuned "
                                  "against DR echoes")
        d = np.flatnonzero(has)
        t = sub.take(d)
        tuning = tune_cfd(t.samples, t.lengths, t.sampling_ns, t.dr_time_ns, feats["FWHM"][d], noise.mean, noise.sd,
                          CFDParams.from_config(cfg), fwhm, tune=bool(sec["tune"]),
                          n_bins=int(cfg["calibrate"]["range_correction_bins"]),
                          min_per_bin=int(cfg["calibrate"]["range_correction_min_pulses"]))
        del sub, t, feats
        cfd, corr = tuning.cfd, tuning.ranges.correction
        level = noise.mean + cfd.arming_sd * noise.sd
        cols = {k: [] for k in ("dr", "res", "amp", "width", "has", "vis", "dt")}
        for batch in iter_pulses(path, batch_rows, columns=COLUMNS):
            p = Pulses.of(batch)
            ech = detect_echoes(p.samples, p.lengths, p.sampling_ns, noise.mean, noise.sd, cfd, 1)
            dr = dr_minus_cfd(p.dr_time_ns, ech.times_ns[:, 0])
            amp = ech.amplitudes[:, 0]
            w = first_echo_features(p.samples, p.lengths, p.sampling_ns, p.dr_time_ns, noise.mean, noise.sd,
                                    fp.segment_sd, fp.peak_rise_sd, echo_search_ns=fp.echo_search_ns)["FWHM"]
            cols["dr"].append(dr.astype(np.float32))
            cols["res"].append((dr - corr(amp)).astype(np.float32))
            cols["amp"].append(amp.astype(np.float32))
            cols["width"].append(w.astype(np.float32))
            cols["has"].append(np.isfinite(p.dr_time_ns))
            cols["vis"].append(dr_visible(p.samples, p.lengths, p.sampling_ns, p.dr_time_ns, level, fwhm / 2))
            cols["dt"].append(p.sampling_ns.astype(np.float32))
            bar.update(batch.num_rows)
    a = {k: np.concatenate(v) for k, v in cols.items()}
    agree = dr_agreement(a["dr"], a["res"], a["has"], a["vis"])
    sampling = float(np.median(a["dt"]))
    result = {
        "dataset": name, "source": str(path), "n_pulses_total": int(n_rows), "n_pulses": agree["n_pulses"],
        "noise_mean": noise.mean, "noise_sd": noise.sd, "noise_sd_analog": noise.sd_analog, "noise_lag1": noise.lag1,
        "noise_quantised": noise.quantised, "noise_n_samples": noise.n_samples, "noise_n_pulses": noise.n_pulses,
        "noise_tail": int(sec["noise_tail"]), "noise_guard_ns": float(sec["noise_guard_ns"]),
        "system_fwhm_ns": fwhm, "fwhm_ns": fwhm, **{k: v for k, v in width_report.items() if k != "system_fwhm_ns"},
        "sampling_ns": sampling,
        "fraction": cfd.fraction, "delay_ns": cfd.delay_ns, "cfd": cfd.to_dict(),
        "range_correction": corr.to_dict(),
        **{k: v for k, v in agree.items() if k != "n_pulses"},
        "criterion": "share of pulses with a DR echo whose first CFD echo, range-corrected, lies within 0.10 m of the "
                     "first DR echo (paper: > 95 %, no bias); counted over all of them, gated share beside it",
        "cfd_tuning": {"tuned": tuning.tuned, "reason": tuning.reason, "n_pulses": int(len(d)),
                       "bias_per_width_class_m": tuning.ranges.class_bias(tuning.classes).tolist(),
                       "width_class_edges_fwhm": list(WIDTH_EDGES), "grid": tuning.grid.to_dict("records")},
    }
    result["note"] = closing_note(agree, sampling, cfd.arming_sd)
    write_json(result, json_path)
    if plot_path is not None:
        plot_cfd_residuals(a["amp"], a["width"] / fwhm, a["res"], a["has"] & np.isfinite(a["dr"]), corr, plot_path,
                           title=f"{name}: CFD vs DR, {_pct(agree['within_0_10_m'])} within 0.10 m "
                                 f"({agree['n_pulses']:,} pulses with a DR echo)",
                           seed=int(cfg["seed"]))
    return result


def _pct(v) -> str:
    return "n/a" if v is None else f"{100 * v:.1f} %"


def summary(res: dict, out) -> str:
    """The one-line CLI summary of a tune-cfd result."""
    med = res["median_residual_m"]
    return (f"tune-cfd: {res['dataset']}: noise {res['noise_mean']:.2f} +- {res['noise_sd']:.2f} DN, system FWHM "
            f"{res['system_fwhm_ns']:.2f} ns, CFD f = {res['fraction']:.2f}, delay {res['delay_ns']:.2f} ns "
            f"({'tuned' if res['cfd_tuning']['tuned'] else 'as configured'}); within 0.10 m of the DR echo: "
            f"{_pct(res['within_0_10_m'])} of {res['n_pulses']:,} pulses (gated {_pct(res['within_0_10_m_gated'])}), "
            f"median residual {'n/a' if med is None else f'{100 * med:.1f} cm'}; wrote {out}")


@click.command("tune-cfd")
@click.argument("pulses", type=EXISTING_FILE)
@click.option("--out", "out", type=OUT_FILE, required=True,
              help="CFD JSON (noise, system FWHM, fraction, delay, range correction, the CFD-DR check).")
@click.option("--plot", "plot", type=OUT_FILE, default=None, help="PNG of the residuals against amplitude and echo width.")
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
@stage_options
def tune_cfd_command(pulses, out, plot, progress, cfg):
    """Tune the CFD on a pulse table's own DR echoes, without calibration targets (docs/own-data.md).

    PULSES is the pulse table of one file (`waveforest ingest` output). Noise from the pulses'
    last samples, the system pulse width from the narrowest single echoes, the CFD fraction,
    delay and range correction by the width-class rule of `calibrate`; reports the share of
    pulses whose first CFD echo lies within 0.10 m of the first DR echo.
    """
    with warnings_to_stderr():
        res = run(pulses, out, cfg, plot_path=plot, progress=progress)
    click.echo(summary(res, out) + (f" and {plot}" if plot else ""))
    click.echo(f"tune-cfd: {res['note']}")
