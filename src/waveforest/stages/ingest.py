"""The ``ingest`` stage: a LAS waveform file -> a pulse table in Parquet.

Reads the options and the config's ``ingest`` streaming sizes and ``agc.attribute``, and calls
:func:`waveforest.io.las.pulses.las_to_pulses`, which streams the file into the table (atomic).
Sensor positions come from a trajectory CSV (``--trajectory``), from a nominal range
(``--nominal-range``), or are left unknown (NaN).
"""

from __future__ import annotations

import click

from waveforest.cliutil import (
    EXISTING_FILE,
    stage_options,
    warnings_to_stderr,
)
from waveforest.io.las.pulses import las_to_pulses


@click.command()
@click.argument("las_file", type=EXISTING_FILE)
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="Output pulse table (Parquet).")
@click.option("--dataset", default=None, help="Dataset name written in every row (default: the LAS file stem).")
@click.option("--trajectory", type=EXISTING_FILE, default=None,
              help="Sensor trajectory CSV (gps_time,x,y,z; linear interpolation) for sensor_xyz and range_m.")
@click.option("--nominal-range", "nominal_range", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Without a trajectory: put the sensor this many metres before the first echo along the beam.")
@click.option("--agc-attribute", default=None,
              help="Point or extra-bytes dimension holding the AGC (default: config agc.attribute, i.e. user_data).")
@click.option("--chunk-points", type=click.IntRange(min=1), default=None,
              help="Points read per chunk (default: config ingest.chunk_points).")
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
@stage_options
def ingest(las_file, out, dataset, trajectory, nominal_range, agc_attribute, chunk_points, progress, cfg):
    """Read a LAS 1.3/1.4 waveform file (point format 4, 5, 9, 10; packets internal or in a .wdp)
    into a Parquet pulse table: one row per pulse (returns grouped by GPS time).

    Example:

    \b
    waveforest ingest flight.las --trajectory flight_trajectory.csv --out pulses.parquet
    """

    icfg = cfg["ingest"]
    with warnings_to_stderr():
        result = las_to_pulses(
            las_file,
            out,
            dataset=dataset,
            trajectory=trajectory,
            nominal_range_m=nominal_range,
            agc_attribute=agc_attribute if agc_attribute is not None else cfg["agc"]["attribute"],
            chunk_points=chunk_points or icfg["chunk_points"],
            bucket_points=icfg["bucket_points"],
            batch_pulses=icfg["batch_pulses"],
            progress=progress,
        )
    click.echo(result.summary())
