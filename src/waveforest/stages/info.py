"""The ``info`` stage: a lasinfo-style summary of one LAS waveform file on stdout.

Reads the file in one streaming pass (:func:`waveforest.io.las.info.summarise`, with the
config's ``ingest`` streaming sizes and ``agc.attribute``); writes nothing. An unusable file
ends in :class:`waveforest.io.las.format.LasWaveformError`.
"""

from __future__ import annotations

import click

from waveforest.cliutil import (
    EXISTING_FILE,
    stage_options,
)
from waveforest.io.las.info import format_summary, summarise
from waveforest.io.las.points_info import is_point_cloud, summarise_point_cloud


@click.command()
@click.argument("las_file", type=EXISTING_FILE)
@click.option("--agc-attribute", default=None,
              help="Point or extra-bytes dimension holding the AGC (default: config agc.attribute, i.e. user_data).")
@stage_options
def info(las_file, agc_attribute, cfg):
    """Summarise a LAS waveform file: version, point format, descriptors, pulses, packets,
    returns, samples per packet, AGC and bounds (like lasinfo).

    A point cloud without waveforms (e.g. the output of `waveforest decompose`) gets its
    header facts, counts, extent and the range of each extra-bytes dimension.

    Example:

    \b
    waveforest info flight.las
    """

    icfg = cfg["ingest"]
    if is_point_cloud(las_file):
        click.echo(summarise_point_cloud(las_file, chunk_points=icfg["chunk_points"]))
        return
    summary = summarise(
        las_file,
        agc_attribute=agc_attribute if agc_attribute is not None else cfg["agc"]["attribute"],
        chunk_points=icfg["chunk_points"],
        bucket_points=icfg["bucket_points"],
    )
    click.echo(format_summary(summary))
