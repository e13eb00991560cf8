"""The ``select`` stage: the pulses that hit field samples (docs/method.md §(i1), i4).

The rules and flags are those of :mod:`waveforest.model.selection`; this module reads the
pulse and campaign tables, applies them and writes the selected pulse table.
"""

from __future__ import annotations

from dataclasses import dataclass

import click
import numpy as np

from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_FILE,
    stage_options,
)
from waveforest.errors import WaveforestError
from waveforest.io.pulses import read_pulses, write_pulses
from waveforest.io.tables import dataset_row, read_datasets, read_fields
from waveforest.model.selection import dataset_of, select_pulses
from waveforest.settings import select_rules


@dataclass(frozen=True)
class SelectSummary:
    """What :func:`run` wrote."""

    dataset: str
    n_pulses: int
    n_selected: int
    n_classification: int
    n_comparison: int
    n_below_crown: int
    n_samples: int


def run(pulses_path, fields_path, datasets_path, out_path, cfg: dict) -> SelectSummary:
    """The ``select`` stage: read a (normalised) pulse table, write the selected pulses.

    Parameters
    ----------
    pulses_path : path
        Pulse table of one dataset (``results/agc/{dataset}.parquet``).
    fields_path, datasets_path : path
        ``fields.csv`` and ``datasets.csv`` of the campaign folder.
    out_path : path
        Output Parquet: the selected pulse rows with the columns of
        :data:`waveforest.model.selection.SELECT_COLUMNS`.
    cfg : dict
        Loaded study config (sections ``select`` and ``simulate``).
    """

    pulses = read_pulses(pulses_path)
    datasets = read_datasets(datasets_path)
    fields = read_fields(fields_path)
    if pulses.num_rows == 0:
        raise WaveforestError(f"{pulses_path}: the pulse table is empty")
    name = dataset_of(pulses, str(pulses_path))
    year = int(dataset_row(datasets, name, datasets_path)["year"])
    if not (fields["year"] == year).any():
        raise WaveforestError(f"{fields_path}: no field sample of year {year} (dataset {name})")
    out = select_pulses(pulses, fields, year, select_rules(cfg))
    write_pulses(out, out_path)
    flags = {c: int(np.count_nonzero(out.column(c).to_numpy(zero_copy_only=False)))
             for c in ("classification_set", "comparison_set", "below_crown_set")}
    return SelectSummary(
        dataset=name, n_pulses=pulses.num_rows, n_selected=out.num_rows,
        n_classification=flags["classification_set"], n_comparison=flags["comparison_set"],
        n_below_crown=flags["below_crown_set"],
        n_samples=len(set(out.column("sample_id").to_pylist())),
    )


@click.command("select")
@click.argument("pulses", type=EXISTING_FILE)
@click.option("--fields", type=EXISTING_FILE, required=True, help="fields.csv of the campaign folder.")
@click.option("--datasets", type=EXISTING_FILE, required=True, help="datasets.csv of the campaign folder.")
@click.option("--out", type=OUT_FILE, required=True, help="Output Parquet: the selected pulses.")
@stage_options
def select(pulses, fields, datasets, out, cfg):
    """Select the pulses whose first echo hits a field sample (docs/method.md §(i1), i4).

    PULSES is the AGC-normalised pulse table of one dataset (results/agc/{dataset}.parquet).
    Adds sample_id, species, functional_group, ground_z, height_m and the flags
    single_echo_set (one DR echo), classification_set (single DR echo, species with
    >= select.min_pulses such pulses in this dataset; classify re-applies the rule across
    datasets), and
    comparison_set (modelled species, birch 2.5-5 m), and below_crown_set: pulses under a
    comparison tree's crown whose first echo is lower than select.tree_min_echo_h_m (for
    diagnose only).

    Example:

    \b
    waveforest select agc.parquet --fields campaign/fields.csv --datasets campaign/datasets.csv --out select.parquet
    """

    s = run(pulses, fields, datasets, out, cfg)
    click.echo(f"select: {s.dataset}: {s.n_selected} of {s.n_pulses} pulses on {s.n_samples} samples "
               f"({s.n_classification} classification, {s.n_comparison} comparison, {s.n_below_crown} below crown) "
               f"-> {out}")
