"""The ``agc`` stage: fit the AGC law of Eq. 1 on the AGC targets and normalise every pulse
(docs/method.md §(b)); the fit is :mod:`waveforest.model.agc_fit`, the pure kernels :mod:`waveforest.sensor.agc`."""

from __future__ import annotations

from pathlib import Path

import click

from waveforest.cliutil import dataset_fit_options, stage_options
from waveforest.errors import WaveforestError
from waveforest.io.results import write_agc_fit
from waveforest.io.tables import read_datasets, read_targets
from waveforest.model.agc_fit import fit_agc, write_normalised
from waveforest.report.plots import plot_cv_curve
from waveforest.sensor.agc import AGCFit
from waveforest.settings import agc_settings


def run(pulses_path, targets, datasets, out_path, fit_path, cfg: dict, *, plot_path=None,
        batch_rows: int = 65536, progress: bool = True) -> AGCFit:
    """The ``agc`` stage: fit b on the AGC targets, normalise every pulse, write both outputs.

    Eq. 1 (docs/method.md §(b)): pass 1 reads the AGC values, the noise floor n0 and the fit
    statistic of the target pulses; the fit; pass 2 writes the normalised pulses.

    Parameters
    ----------
    pulses_path : pulse table of one dataset (Parquet).  targets, datasets : DataFrames of
    targets.csv / datasets.csv (see :mod:`waveforest.sensor.targets`).  out_path : normalised
    pulse table (Parquet, with :data:`GAIN_COLUMN` and schema metadata a, b, n0).
    fit_path : JSON of the :class:`AGCFit`.  cfg : validated config (:func:`waveforest.config.validate`;
    sections agc, calibrate, sensor).
    plot_path : optional PNG of CV(b).

    Returns
    -------
    AGCFit

    Raises
    ------
    WaveforestError
        Missing or empty table, several datasets, no samples for n0, too few target pulses to fit b.
    """
    pulses_path = Path(pulses_path)
    if not pulses_path.exists():
        raise WaveforestError(f"{pulses_path}: no such file")
    fit = fit_agc(pulses_path, targets, datasets, agc_settings(cfg), batch_rows, progress)
    write_normalised(pulses_path, fit, out_path, batch_rows, progress)
    write_agc_fit(fit.to_dict(), fit_path)
    if plot_path is not None and len(fit.b_grid):
        plot_cv_curve(fit, plot_path)
    return fit


@click.command()
@dataset_fit_options("Normalised pulse table (Parquet).",
                     ("--fit", "fit", "Fit of Eq. 1 (JSON: a, b, CV before/after, ...)."), "Optional PNG of CV(b).")
@stage_options
def agc(pulses, targets_csv, datasets_csv, out, fit, plot, cfg):
    """Fit the AGC law on AGC targets; normalise waveforms and intensities (docs/method.md §(b), Eq. 1).

    PULSES is the pulse table of one dataset (`waveforest ingest` output).

    Example:

    \b
    waveforest agc results/pulses/2010_12_1.parquet --targets campaign/targets.csv --datasets campaign/datasets.csv --out agc.parquet --fit agc.json
    """

    res = run(pulses, read_targets(targets_csv), read_datasets(datasets_csv), out, fit, cfg, plot_path=plot)
    click.echo(f"agc: {res.dataset}: a = {res.a:.3f}, b = {res.b:.6f}, nested CV {100 * res.cv_before:.2f} % -> "
               f"{100 * res.cv_after:.2f} % on {res.n_fit_pulses} target pulses; wrote {res.n_pulses_total} pulses "
               f"to {out} and the fit to {fit}")
