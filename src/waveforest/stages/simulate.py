"""The ``simulate`` stage: twins of the selected real pulses (docs/method.md §(i1)).

The chain (vegetation instances, MCRT, sensor model, CFD; chunks and seeds) is
:mod:`waveforest.model.simulate`; this module reads the select table, the dataset's row and
calibration, runs it for one chunk and writes the simulated pulse table.
"""

from __future__ import annotations

from pathlib import Path

import click

from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_FILE,
    stage_options,
)
from waveforest.effects import parse_effects
from waveforest.io.pulses import write_pulses
from waveforest.io.results import read_select_table
from waveforest.io.tables import dataset_row, read_datasets, read_fields
from waveforest.model.selection import dataset_of
from waveforest.model.simulate import SimulateSummary, simulate_pulses, with_sample_columns
from waveforest.sensor.calibration import load_calibration
from waveforest.settings import simulate_settings


def run(selected_path, datasets_path, system_path, calibration_path, out_path, cfg: dict, *,
        chunk: int = 0, chunks: int | None = None, effects: dict | None = None,
        fields_path=None) -> SimulateSummary:
    """The ``simulate`` stage for one dataset and chunk: read, simulate, write atomically.

    ``fields_path`` (optional) supplies sample_x, sample_y and height_m when the select table
    lacks them (tables selected by other tools); ``select`` writes them itself.
    """

    selected = read_select_table(selected_path)
    if fields_path is not None:
        selected = with_sample_columns(selected, read_fields(fields_path), str(fields_path))
    chunks = int(cfg["simulate"]["chunks"] if chunks is None else chunks)
    datasets = read_datasets(datasets_path)
    if selected.num_rows:
        name = dataset_of(selected, str(selected_path))
    else:
        name = Path(selected_path).stem
    info = dataset_row(datasets, name, datasets_path)
    cal = load_calibration(calibration_path, system_path)
    table, summary = simulate_pulses(selected, info, cal, simulate_settings(cfg), chunk=chunk, chunks=chunks,
                                     effects=effects)
    write_pulses(table, out_path)
    return summary


@click.command("simulate")
@click.argument("selected", type=EXISTING_FILE)
@click.option("--fields", type=EXISTING_FILE, default=None,
              help="fields.csv: sample positions and heights when the select table lacks them.")
@click.option("--datasets", type=EXISTING_FILE, required=True, help="datasets.csv of the campaign folder.")
@click.option("--system", type=EXISTING_FILE, required=True, help="Calibrated S(t) of the dataset (Parquet).")
@click.option("--calibration", type=EXISTING_FILE, required=True, help="Calibration JSON (noise_mean, noise_sd).")
@click.option("--chunk", type=click.IntRange(min=0), default=0, show_default=True, help="Chunk index, 0 .. chunks-1.")
@click.option("--chunks", type=click.IntRange(min=1), default=None, help="Number of chunks (default simulate.chunks).")
@click.option("--effect", "effects", multiple=True, metavar="NAME=VALUE",
              help="Add an effect to the model (src/waveforest/effects.py); repeatable. Overrides simulate.effects.")
@click.option("--out", type=OUT_FILE, required=True, help="Output Parquet: the simulated pulse table (source = sim).")
@stage_options
def simulate(selected, fields, datasets, system, calibration, chunk, chunks, effects, out, cfg):
    """Simulate the selected pulses of the modelled species: vegetation instance, MCRT, sensor.

    SELECTED is the dataset's select table. The pulses of field samples assigned to chunk
    CHUNK (a stable hash of the sample and its vegetation instance) are simulated with the
    real pulse geometry, the dataset's S(t) and noise, and written with source = sim and
    the real pulse_id.

    Example:

    \b
    waveforest simulate select.parquet --datasets campaign/datasets.csv --system system.parquet --calibration calibration.json --out sim.parquet
    """

    eff = dict(cfg["simulate"]["effects"])
    eff.update(parse_effects(list(effects)))
    n_chunks = cfg["simulate"]["chunks"] if chunks is None else chunks
    s = run(selected, datasets, system, calibration, out, cfg, chunk=chunk, chunks=n_chunks, effects=eff,
            fields_path=fields)
    click.echo(f"simulate: {s.dataset} chunk {chunk}/{n_chunks}: {s.n_written} of {s.n_pulses} pulses "
               f"({s.n_instances} vegetation instances, {s.n_no_echo} without echo) -> {out}")
