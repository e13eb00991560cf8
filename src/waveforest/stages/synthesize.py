"""The ``synthesize`` stage."""

from __future__ import annotations

import click

from waveforest.campaign.synthesize import run
from waveforest.cliutil import (
    force_option,
    stage_options,
)
from waveforest.effects import CATALOGUE
from waveforest.settings import campaign_settings

_EFFECT_HELP = "; ".join(f"{e.name} (off {e.off:g}, e.g. {e.test_value:g}): {e.description}"
                         for e in CATALOGUE.values())


@click.command(short_help="Generate the virtual ALS60 campaign folder (hidden effects optional).",
               help=f"""Generate the virtual ALS60 campaign (LAS waveform files, field and target
tables, trajectories, truth.json) into OUT, in the layout of a real campaign folder.

Hidden effects (--effect NAME=VALUE, repeatable, on top of the config's campaign.effects):
{_EFFECT_HELP}.""")
@click.option("--out", "out_dir", required=True, type=click.Path(file_okay=False),
              help="Campaign folder to write (an earlier campaign there is replaced whole; a folder holding "
                   "anything else is refused unless --force).")
@click.option("--effect", "effects", multiple=True, metavar="NAME=VALUE",
              help="Switch on a hidden effect in the campaign (repeatable).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
@force_option
@stage_options
def synthesize(out_dir, effects, quiet, force, cfg):
    """Generate the virtual campaign."""

    summary = run(campaign_settings(cfg), out_dir, effects=list(effects), progress=not quiet, force=force)
    click.echo(summary.line())
