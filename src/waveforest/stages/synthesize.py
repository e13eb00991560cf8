"""The ``synthesize`` stage."""

from __future__ import annotations

import click

from waveforest.campaign.synthesize import run
from waveforest.cliutil import (
    stage_options,
)
from waveforest.effects import CATALOGUE

_EFFECT_HELP = "; ".join(f"{e.name} (off {e.off:g}, e.g. {e.test_value:g}): {e.description}"
                         for e in CATALOGUE.values())


@click.command(short_help="Generate the virtual ALS60 campaign folder (hidden effects optional).",
               help=f"""Generate the virtual ALS60 campaign (LAS waveform files, field and target
tables, trajectories, truth.json) into OUT, in the layout of a real campaign folder.

Hidden effects (--effect NAME=VALUE, repeatable, on top of the config's campaign.effects):
{_EFFECT_HELP}.""")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Campaign folder to write (replaced atomically if it exists).")
@click.option("--effect", "effects", multiple=True, metavar="NAME=VALUE",
              help="Switch on a hidden effect in the campaign (repeatable).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@stage_options
def synthesize(out_dir, effects, quiet, cfg):
    """Generate the virtual campaign."""

    summary = run(cfg, out_dir, effects=list(effects), progress=not quiet)
    click.echo(summary.line())
