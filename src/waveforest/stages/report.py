"""The ``report`` stage."""

from __future__ import annotations

from pathlib import Path

import click

from waveforest.cliutil import (
    stage_options,
)
from waveforest.report.build import run


@click.command("report")
@click.option("--results", type=click.Path(exists=True, file_okay=False, path_type=Path), default=Path("results"),
              show_default=True, help="Results folder of the run.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Output HTML (results/report/report.html).")
@click.option("--markdown", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output Markdown (default: beside --out, suffix .md).")
@stage_options
def report(results, out, markdown, cfg):
    """One HTML page and a Markdown twin with every table and figure of a run.

    Also writes table4.csv and table4.md (Table 4 analogue with the paper's values) beside
    the report, and lists the config used and the software versions.
    """

    r = run(results, out, cfg, markdown)
    click.echo(f"report: {r.n_sections} sections, {r.n_tables} tables, {r.n_figures} figures -> {r.html}, {r.markdown}")
