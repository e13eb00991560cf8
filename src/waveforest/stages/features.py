"""The ``features`` stage."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np
import pandas as pd
import pyarrow as pa

from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_FILE,
    stage_options,
)
from waveforest.errors import WaveforestError
from waveforest.io.pulses import check_pulses, iter_pulses, write_table
from waveforest.sensor.calibration import load_calibration
from waveforest.sensor.features import FEATURE_NAMES, feature_table
from waveforest.sensor.params import CFDParams, FeatureParams


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

    from tqdm import tqdm

    noise, corrections, cfd = {}, {}, {}
    use_rc = bool(cfg["sensor"]["cfd"]["range_correction"])
    for p in calibration_paths:
        cal = load_calibration(p)
        noise[cal.dataset] = cal.meta
        cfd[cal.dataset] = cal.cfd or CFDParams.from_config(cfg)
        if use_rc:
            corrections[cal.dataset] = cal.range_correction_or_identity()
    params = FeatureParams.from_config(cfg)
    parts = []
    for path in pulse_paths:
        path = Path(path)
        if not path.exists():
            raise WaveforestError(f"{path}: no such file")
        for batch in tqdm(iter_pulses(path, batch_rows), desc=f"features: {path.name}", unit="batch",
                          disable=not progress):
            batch = check_pulses(batch, path)
            names = set(np.unique(batch.column("dataset").to_numpy(zero_copy_only=False).astype(str)))
            unknown = sorted(names - set(noise))
            if unknown:
                raise WaveforestError(
                    f"{path}: dataset(s) {', '.join(unknown)} have no calibration JSON among "
                    f"{', '.join(map(str, calibration_paths)) or '(none)'}")
            parts.append(feature_table(batch, noise, params, cfd=cfd, range_corrections=corrections))
    df = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(
        columns=["dataset", "pulse_id", "source", "n_echoes", "echo_time_ns", *FEATURE_NAMES, "H", "echo_z"])
    write_table(pa.Table.from_pandas(df, preserve_index=False), out_path)
    return df


@click.command()
@click.argument("pulses", type=EXISTING_FILE, nargs=-1, required=True)
@click.option("--calibration", "calibration", type=EXISTING_FILE, multiple=True, required=True,
              help="Calibration JSON(s) giving each dataset's noise mean and SD (repeatable).")
@click.option("--out", "out", type=OUT_FILE, required=True, help="Feature table (Parquet).")
@stage_options
def features(pulses, calibration, out, cfg):
    """First-echo waveform features (Npeaks, Apeak, FWHM, E, H) of real or simulated pulses (docs/method.md §(h)).

    PULSES are one or more pulse tables (e.g. the chunks of `waveforest simulate`).
    """

    df = run(list(pulses), list(calibration), out, cfg)
    ok = int(df["Apeak"].notna().sum()) if len(df) else 0
    click.echo(f"features: {len(df)} pulses ({ok} with a first-echo segment) from {len(pulses)} file(s) -> {out}")
