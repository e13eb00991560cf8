"""The ``tune-cfd`` stage: noise, system pulse width, CFD and range correction of one pulse table
from its own DR echoes, and the paper's CFD-DR check on every pulse (docs/own-data.md).

Builds the settings from the config, calls :func:`waveforest.model.self_tuning.tune_pulse_table`
and writes its JSON and, if asked, the residual plot.
"""

from __future__ import annotations

import click

from waveforest import settings
from waveforest.atomic import write_json
from waveforest.cliutil import EXISTING_FILE, OUT_FILE, stage_options, warnings_to_stderr
from waveforest.model.self_tuning import STREAM_ROWS, summary_line, tune_pulse_table
from waveforest.report.quicklook import plot_self_tuning


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
    tuned = tune_pulse_table(pulses_path, settings.self_tuning_settings(cfg), batch_rows=batch_rows, progress=progress)
    write_json(tuned.result, json_path)
    if plot_path is not None:
        plot_self_tuning(tuned, plot_path, seed=int(cfg["seed"]))
    return tuned.result


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

    Example:

    \b
    waveforest tune-cfd pulses.parquet --out cfd.json --plot cfd.png
    """
    with warnings_to_stderr():
        res = run(pulses, out, cfg, plot_path=plot, progress=progress)
    click.echo(summary_line(res, out) + (f" and {plot}" if plot else ""))
    click.echo(f"tune-cfd: {res['note']}")
