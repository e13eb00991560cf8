"""The ``features`` stage.

With calibration JSONs (``--calibration``, the study's path) it writes the first-echo features
of docs/method.md §(h) (:func:`waveforest.model.features.calibrated_features`). With the JSON of
``tune-cfd`` (``--cfd``, a user's own file without targets) it streams the table and adds, per
pulse, the first echo's x and y and every echo of the tuned CFD, range-corrected, as list
columns (:func:`waveforest.model.features.cfd_features`).
"""

from __future__ import annotations

import click
import pandas as pd

from waveforest import settings
from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_FILE,
    stage_options,
    warnings_to_stderr,
)
from waveforest.io.results import write_feature_table
from waveforest.model.features import calibrated_features, cfd_features


def run(pulse_paths, calibration_paths, out_path, cfg: dict, *, batch_rows: int = 65536,
        progress: bool = True) -> pd.DataFrame:
    """The ``features`` stage: first-echo features of one or more pulse tables -> one Parquet.

    Parameters
    ----------
    pulse_paths : pulse tables (real, AGC-normalised, or simulated chunks) -- read in batches.
    calibration_paths : calibration JSONs (``calibrate`` output) giving each dataset's noise.
    out_path : feature table (Parquet).  cfg : validated config (sections sensor.features, sensor.cfd).

    Returns
    -------
    pandas.DataFrame, the table written.
    """
    df = calibrated_features(pulse_paths, calibration_paths, settings.feature_table_settings(cfg),
                             batch_rows=batch_rows, progress=progress)
    write_feature_table(df, out_path)
    return df


@click.command()
@click.argument("pulses", type=EXISTING_FILE, nargs=-1, required=True)
@click.option("--calibration", "calibration", type=EXISTING_FILE, multiple=True,
              help="Calibration JSON(s) giving each dataset's noise mean and SD (repeatable).")
@click.option("--cfd", "cfd", type=EXISTING_FILE, default=None,
              help="Instead of calibrations: the JSON of `waveforest tune-cfd` (noise, CFD, range correction); "
                   "adds every CFD echo (time, range, XYZ, amplitude) as list columns.")
@click.option("--out", "out", type=OUT_FILE, required=True, help="Feature table (Parquet).")
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
@stage_options
def features(pulses, calibration, cfd, out, progress, cfg):
    """First-echo waveform features (Npeaks, Apeak, FWHM, E, H) of real or simulated pulses (docs/method.md §(h)).

    PULSES are one or more pulse tables (e.g. the chunks of `waveforest simulate`). Give either
    --calibration (the study) or --cfd (one file tuned by `waveforest tune-cfd`, no targets needed).

    Example:

    \b
    waveforest features pulses.parquet --cfd cfd.json --out features.parquet
    """
    if bool(calibration) == bool(cfd):
        raise click.UsageError("give either --calibration (one or more) or --cfd, not both and not neither")
    if cfd:
        with warnings_to_stderr():
            res = cfd_features(list(pulses), cfd, out, settings.feature_table_settings(cfg), progress=progress)
        click.echo(f"features: {res.n_pulses:,} pulses ({res.n_with_segment:,} with a first-echo segment, "
                   f"{res.n_cfd_echoes:,} CFD echoes) from {len(pulses)} file(s) -> {out}")
        return
    df = run(list(pulses), list(calibration), out, cfg, progress=progress)
    ok = int(df["Apeak"].notna().sum()) if len(df) else 0
    click.echo(f"features: {len(df)} pulses ({ok} with a first-echo segment) from {len(pulses)} file(s) -> {out}")
