"""The ``waveforest diagnose`` command."""

from __future__ import annotations

from pathlib import Path

import click

from ..analysis.cli import MultiValueCommand, MultiValueOption
from ..cliutil import stage_options

_FILE = click.Path(exists=True, dir_okay=False, path_type=Path)
_DIR = click.Path(file_okay=False, path_type=Path)
_EXISTING_DIR = click.Path(exists=True, file_okay=False, path_type=Path)


@click.command("diagnose", cls=MultiValueCommand)
@click.option("--selected", "selected", cls=MultiValueOption, type=_FILE, required=True,
              help="select tables of the diagnosed datasets (results/select/{dataset}.parquet).")
@click.option("--features-real", "features_real", cls=MultiValueOption, type=_FILE, required=True,
              help="Real feature tables (results/features/{dataset}_real.parquet).")
@click.option("--calibration", "calibration", cls=MultiValueOption, type=_FILE, required=True,
              help="Calibration JSONs (results/calibration/{dataset}.json).")
@click.option("--system", "system", cls=MultiValueOption, type=_FILE,
              help="S(t) Parquet files (results/calibration/{dataset}.parquet); default: beside each JSON.")
@click.option("--agc", "agc", cls=MultiValueOption, type=_FILE,
              help="AGC-normalised pulse tables (results/agc/{dataset}.parquet): their calibration-target "
                   "pulses recalibrate S(t) under each value of the candidates nonlinearity and trigger_loss; "
                   "without them those candidates act on top of the calibrated S(t).")
@click.option("--campaign", "campaign", type=_EXISTING_DIR, required=True,
              help="Campaign folder (its datasets.csv and targets.csv; fields.csv if present).")
@click.option("--out", "out", type=_DIR, required=True,
              help="Output folder: model.yaml, candidates.csv, gap_before_after.csv, gap.png, "
                   "signatures.csv, diagnose.md.")
@stage_options
def diagnose(selected, features_real, calibration, system, agc, campaign, out, cfg):
    """Find where simulation and measurement disagree, name the missing effect, show the gap shrink.

    Beyond the paper: each effect of the catalogue (src/waveforest/effects.py) is fitted on
    one half of the field samples and tested on the other (config section `diagnose`).
    """
    from .run import run

    fields = campaign / "fields.csv"
    res = run(list(selected), list(features_real), list(calibration), out, cfg,
              datasets_path=campaign / "datasets.csv", system_paths=list(system or ()),
              fields_path=fields if fields.exists() else None, agc_paths=list(agc or ()),
              targets_path=campaign / "targets.csv")
    named = ", ".join(f"{k} = {v:.3g}" for k, v in res.effects.items()) or "nothing named"
    click.echo(f"diagnose: verdict {res.verdict} ({named}); gap {res.gap_before:.3g} -> {res.gap_after:.3g}; "
               f"{res.n_pulses} pulses, {res.n_samples} samples, {res.n_simulations} simulations, "
               f"{res.seconds:.0f} s -> {out}")
