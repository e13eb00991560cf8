"""The ``compare`` stage: Table 3, Fig. 6 and Fig. 7 analogues (:mod:`waveforest.analysis.compare`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click
import pandas as pd

from waveforest.analysis.compare import (
    WAVEFORM_GRID_NS,
    compare_features,
    figure_panels,
    overlay_waveforms,
)
from waveforest.atomic import OutputFolder, atomic_path
from waveforest.cliutil import OUT_DIR, MultiValueCommand, force_option, input_files_option, stage_options
from waveforest.io.results import attach_selection, read_feature_tables, read_select_columns
from waveforest.report import plots
from waveforest.report.markdown import to_markdown
from waveforest.settings import compare_settings

SELECT_SCALARS = ["dataset", "pulse_id", "comparison_set", "height_m", "first_echo_h_m"]
"""Columns compare reads from select tables (those a table has)."""


@dataclass(frozen=True)
class CompareOutputs:
    """Files written by :func:`run`."""

    table_csv: Path
    table_md: Path
    order_csv: Path
    figures: list


def run(real_paths, sim_paths, select_paths, sim_pulse_paths, out_dir, cfg: dict, *,
        force: bool = False) -> CompareOutputs:
    """The ``compare`` stage.

    Parameters
    ----------
    real_paths : paths
        Feature tables of the selected real pulses (``results/features/{dataset}_real.parquet``).
    sim_paths : paths
        Feature tables of the simulated pulses (``results/features/{dataset}_sim.parquet``).
    select_paths : paths
        ``select`` tables (flags ``comparison_set``, and the real waveforms for Fig. 7).
    sim_pulse_paths : paths
        ``simulate`` chunk tables (the simulated waveforms for Fig. 7); may be empty.
    out_dir : path
        Writes ``table3.csv``, ``table3.md``, ``order_check.csv``, ``fig6_{dataset}.png`` and
        ``fig7_{dataset}.png`` (whole or not at all: :class:`waveforest.atomic.OutputFolder`).
    cfg : dict
        Loaded study config (``simulate.species``, ``simulate.datasets``, ``simulate.compare_min_h_m``, ``seed``).
    """
    settings = compare_settings(cfg)
    folder = OutputFolder(out_dir, "compare", force=force)
    real = read_feature_tables(real_paths)
    sim = read_feature_tables(sim_paths)
    if select_paths:
        real = attach_selection(real, read_select_columns(select_paths, SELECT_SCALARS, required=()))
    comparison = compare_features(real, sim, settings)
    t3, checks = comparison.table, comparison.checks
    with folder as out:
        paths = {"csv": out / "table3.csv", "md": out / "table3.md", "order": out / "order_check.csv"}
        with atomic_path(paths["csv"]) as tmp:
            t3.to_csv(tmp, index=False, float_format="%.6g")
        with atomic_path(paths["order"]) as tmp:
            checks.to_csv(tmp, index=False, float_format="%.6g")
        with atomic_path(paths["md"]) as tmp:
            tmp.write_text(markdown_report(t3, checks))
        figures = []
        real_wf, sim_wf = overlay_waveforms(comparison, select_paths, sim_pulse_paths, settings.seed)
        for ds, heights_r, heights_s, aligned in figure_panels(comparison, settings.species, real_wf, sim_wf):
            figures.append(plots.fig6_heights(heights_r, heights_s, ds, out / f"fig6_{ds}.png"))
            figures.append(plots.fig7_waveforms(aligned, WAVEFORM_GRID_NS, ds, out / f"fig7_{ds}.png"))
    return CompareOutputs(folder.final(paths["csv"]), folder.final(paths["md"]), folder.final(paths["order"]),
                          [folder.final(f) for f in figures])


def markdown_report(t3: pd.DataFrame, checks: pd.DataFrame) -> str:
    """table3.md: our Table 3 with the paper's simulated values, and the order checks."""
    cols = ["dataset", "species", "feature", "sim_mean", "sim_sd", "real_mean", "real_sd", "delta_pct",
            "n_sim", "n_real", "paper_sim_mean", "paper_sim_sd", "paper_real_mean", "paper_delta_pct"]
    text = ["# Real vs simulated first-echo features (Table 3 analogue)", "",
            "Delta % = (sim - real) / real x 100. `paper_*`: Hovi & Korpela (2014) Table 3. "
            "Birch waveform features use echoes with H > 1.5 m only.", "",
            to_markdown(t3[cols]), "",
            "## Species order and FWHM vs the paper's simulation", "",
            to_markdown(checks)]
    return "\n".join(text)


@click.command("compare", cls=MultiValueCommand)
@input_files_option("--real", "real", "Feature tables of the selected real pulses (one or more).", required=True)
@input_files_option("--sim", "sim", "Feature tables of the simulated pulses (one or more).", required=True)
@input_files_option("--pulses-real", "pulses_real", "select tables (comparison flags and real waveforms).")
@input_files_option("--pulses-sim", "pulses_sim", "simulate chunk tables (simulated waveforms).")
@click.option("--out", type=OUT_DIR, required=True, help="Output folder (table3.csv, table3.md, fig6_*, fig7_*).")
@force_option
@stage_options
def compare(real, sim, pulses_real, pulses_sim, out, force, cfg):
    """Real vs simulated features: the Table 3 analogue and Figures 6-7 (docs/method.md §(i1)).

    Example:

    \b
    waveforest compare --real real.parquet --sim sim.parquet --out compare/
    """

    r = run(real, sim, pulses_real, pulses_sim, out, cfg, force=force)
    click.echo(f"compare: {r.table_csv}, {r.table_md}, {r.order_csv} and {len(r.figures)} figures")
