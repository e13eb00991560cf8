"""``waveforest ingest`` and ``waveforest info``: LAS waveform files in, pulse tables out."""

from __future__ import annotations

import contextlib
import sys
import warnings

import click
from tqdm import tqdm

from ..cliutil import stage_options


@contextlib.contextmanager
def _warnings_to_stderr():
    """Show every warning once as ``waveforest: warning: ...`` (clear of progress bars)."""

    def show(message, category, filename, lineno, file=None, line=None):
        tqdm.write(f"waveforest: warning: {message}", file=sys.stderr)

    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = show
        yield


@click.command()
@click.argument("las_file", type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False), help="Output pulse table (Parquet).")
@click.option("--dataset", default=None, help="Dataset name written in every row (default: the LAS file stem).")
@click.option("--trajectory", type=click.Path(dir_okay=False), default=None,
              help="Sensor trajectory CSV (gps_time,x,y,z; linear interpolation) for sensor_xyz and range_m.")
@click.option("--nominal-range", "nominal_range", type=float, default=None,
              help="Without a trajectory: put the sensor this many metres before the first echo along the beam.")
@click.option("--agc-attribute", default=None,
              help="Point or extra-bytes dimension holding the AGC (default: config agc.attribute, i.e. user_data).")
@click.option("--chunk-points", type=click.IntRange(min=1), default=None,
              help="Points read per chunk (default: config ingest.chunk_points).")
@click.option("--progress/--no-progress", default=True, help="Progress bar on stderr.")
@stage_options
def ingest(las_file, out, dataset, trajectory, nominal_range, agc_attribute, chunk_points, progress, cfg):
    """Read a LAS 1.3/1.4 waveform file (point format 4, 5, 9, 10; packets internal or in a .wdp)
    into a Parquet pulse table: one row per pulse (returns grouped by GPS time)."""
    from .ingest import run

    icfg = cfg["ingest"]
    with _warnings_to_stderr():
        result = run(
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


@click.command()
@click.argument("las_file", type=click.Path(dir_okay=False))
@click.option("--agc-attribute", default=None,
              help="Point or extra-bytes dimension holding the AGC (default: config agc.attribute, i.e. user_data).")
@stage_options
def info(las_file, agc_attribute, cfg):
    """Summarise a LAS waveform file: version, point format, descriptors, pulses, packets,
    returns, samples per packet, AGC and bounds (like lasinfo)."""
    from .las_info import format_summary, summarise

    icfg = cfg["ingest"]
    summary = summarise(
        las_file,
        agc_attribute=agc_attribute if agc_attribute is not None else cfg["agc"]["attribute"],
        chunk_points=icfg["chunk_points"],
        bucket_points=icfg["bucket_points"],
    )
    click.echo(format_summary(summary))
