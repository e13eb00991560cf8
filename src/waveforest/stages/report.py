"""The ``report`` stage: every table and figure of a run in one HTML page and its Markdown twin,
led by what the run ran on (:mod:`waveforest.report.source`) and a summary of the results beside
the paper's (:mod:`waveforest.report.summary`)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import click
import yaml

from waveforest import config
from waveforest.atomic import atomic_path, output_files
from waveforest.cliutil import stage_options
from waveforest.report.build import collect, render_html, render_markdown
from waveforest.settings import report_settings


@dataclass(frozen=True)
class ReportOutputs:
    """What :func:`run` wrote, and how much of it."""

    html: Path
    markdown: Path
    n_sections: int
    n_tables: int
    n_figures: int


def run(results, out_html, cfg: dict | None, out_md=None, title: str = "waveforest study report",
        config_path=None) -> ReportOutputs:
    """The ``report`` stage: write the HTML page, its Markdown twin and table4.csv/md beside them.

    ``config_path``: the config file ``cfg`` was read from, named in the report (None: defaults).
    """
    out_html = Path(out_html)
    out_md = Path(out_md) if out_md else out_html.with_suffix(".md")
    config_yaml = yaml.safe_dump(cfg, sort_keys=True).strip() if cfg else None
    settings = report_settings(cfg if cfg else config.load(None))
    if not cfg:  # no config: the schema's defaults, and no datasets named for the run
        settings = replace(settings, datasets=())
    made = not out_html.parent.exists()
    out_html.parent.mkdir(parents=True, exist_ok=True)
    try:
        with output_files():  # the page, its twin and table4.csv/md together, or none of them
            sections = collect(results, settings, out_html.parent, config_yaml,
                               None if config_path is None else str(config_path), config.changes(cfg) if cfg else ())
            with atomic_path(out_html) as tmp:
                tmp.write_text(render_html(sections, title))
            with atomic_path(out_md) as tmp:
                tmp.write_text(render_markdown(sections, title, out_md.parent))
    except BaseException:
        if made and not any(out_html.parent.iterdir()):
            out_html.parent.rmdir()  # no empty folder left behind
        raise
    items = [i for s in sections for i in s.items]
    return ReportOutputs(out_html, out_md, len(sections), sum(i[0] == "table" for i in items),
                         sum(i[0] == "figure" for i in items))


@click.command("report")
@click.argument("inputs", nargs=-1, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--results", type=click.Path(exists=True, file_okay=False, path_type=Path), default=Path("results"),
              show_default=True, help="Results folder of the run.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Output HTML file (required; the workflow writes results/report/report.html).")
@click.option("--markdown", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output Markdown (default: beside --out, suffix .md).")
@click.option("--study-config", default=None,
              help="The config file(s) the study ran with, as the report names them (default: --config).")
@stage_options
def report(inputs, results, out, markdown, study_config, cfg):
    """One HTML page and a Markdown twin with every table and figure of a run.

    The report opens with what the run ran on (data source, config and its differences from the
    defaults, datasets, pulse counts beside the paper's; the code's git commit, the size and
    SHA-256 of every input file, the machine), then a summary: Table 3 and Table 4
    beside the paper's values, the Fig. 9 trend and the diagnosis verdict with its detection
    limits; a missing value says why in place. Details follow, calibration after the results.

    INPUTS are result files the report must find (the workflow passes the tables of the stages
    it reports on; a missing one is an error). The report shows everything under --results.

    Also writes table4.csv and table4.md (Table 4 analogue with the paper's values) beside
    the report, and lists the config used and the software versions.

    Example:

    \b
    waveforest report --results results --out results/report/report.html
    """

    r = run(results, out, cfg, markdown,
            config_path=study_config or click.get_current_context().params.get("config_path"))
    click.echo(f"report: {r.n_sections} sections, {r.n_tables} tables, {r.n_figures} figures -> {r.html}, {r.markdown}")
