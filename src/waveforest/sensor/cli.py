"""Click commands of the sensor stages: ``agc``, ``calibrate``, ``features`` (thin wrappers).

Heavy imports (Numba kernels, pandas) happen inside the commands so that
``waveforest --help`` stays fast.
"""

from __future__ import annotations

import json

import click

from ..cliutil import stage_options

_FILE = click.Path(dir_okay=False)
_EXISTING = click.Path(exists=True, dir_okay=False)


@click.command()
@click.argument("pulses", type=_EXISTING)
@click.option("--targets", "targets_csv", type=_EXISTING, required=True, help="targets.csv of the campaign.")
@click.option("--datasets", "datasets_csv", type=_EXISTING, required=True, help="datasets.csv of the campaign.")
@click.option("--out", "out", type=_FILE, required=True, help="Normalised pulse table (Parquet).")
@click.option("--fit", "fit", type=_FILE, required=True, help="Fit of Eq. 1 (JSON: a, b, CV before/after, ...).")
@click.option("--plot", "plot", type=_FILE, default=None, help="Optional PNG of CV(b).")
@stage_options
def agc(pulses, targets_csv, datasets_csv, out, fit, plot, cfg):
    """Fit the AGC law on AGC targets; normalise waveforms and intensities (METHOD b, Eq. 1).

    PULSES is the pulse table of one dataset (`waveforest ingest` output).
    """
    from ..analysis.campaign_tables import read_datasets, read_targets
    from .agc import run

    res = run(pulses, read_targets(targets_csv), read_datasets(datasets_csv), out, fit, cfg, plot_path=plot)
    click.echo(f"agc: {res.dataset}: a = {res.a:.3f}, b = {res.b:.6f}, nested CV {100 * res.cv_before:.2f} % -> "
               f"{100 * res.cv_after:.2f} % on {res.n_fit_pulses} target pulses; wrote {res.n_pulses_total} pulses "
               f"to {out} and the fit to {fit}")


@click.command()
@click.argument("pulses", type=_EXISTING)
@click.option("--targets", "targets_csv", type=_EXISTING, required=True, help="targets.csv of the campaign.")
@click.option("--datasets", "datasets_csv", type=_EXISTING, required=True, help="datasets.csv of the campaign.")
@click.option("--out", "out", type=_FILE, required=True, help="System waveform S(t) (Parquet: t_ns, s, s_sd).")
@click.option("--json", "json_out", type=_FILE, required=True, help="Calibration JSON (noise, FWHM, counts, a, b, CFD check).")
@click.option("--plot", "plot", type=_FILE, default=None, help="Optional PNG of S(t) with its spread.")
@click.option("--agc-fit", "agc_fit", type=_EXISTING, default=None,
              help="The agc step's JSON (a, b, n0), if the table lacks them in its metadata.")
@stage_options
def calibrate(pulses, targets_csv, datasets_csv, out, json_out, plot, agc_fit, cfg):
    """System waveform S(t) and noise of one dataset from reference targets (Eq. 8, METHOD e).

    PULSES is the AGC-normalised pulse table of one dataset (`waveforest agc` output).
    """
    from ..analysis.campaign_tables import read_datasets, read_targets
    from .calibration import run

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


@click.command()
@click.argument("pulses", type=_EXISTING, nargs=-1, required=True)
@click.option("--calibration", "calibration", type=_EXISTING, multiple=True, required=True,
              help="Calibration JSON(s) giving each dataset's noise mean and SD (repeatable).")
@click.option("--out", "out", type=_FILE, required=True, help="Feature table (Parquet).")
@stage_options
def features(pulses, calibration, out, cfg):
    """First-echo waveform features (Npeaks, Apeak, FWHM, E, H) of real or simulated pulses (METHOD h).

    PULSES are one or more pulse tables (e.g. the chunks of `waveforest simulate`).
    """
    from .features import run

    df = run(list(pulses), list(calibration), out, cfg)
    ok = int(df["Apeak"].notna().sum()) if len(df) else 0
    click.echo(f"features: {len(df)} pulses ({ok} with a first-echo segment) from {len(pulses)} file(s) -> {out}")
