"""Commands of the analysis stages: select, simulate, compare, sensitivity, sensor-study, classify.

Each command parses its options, calls the ``run`` function of its module and prints one
line saying what it wrote. Options that take several files accept them after one flag
(``--real a.parquet b.parquet``, as Snakemake expands a list) or repeated.
"""

from __future__ import annotations

from pathlib import Path

import click

from ..cliutil import stage_options


class MultiValueOption(click.Option):
    """An option that takes one or more values after a single flag (and may also repeat)."""

    def __init__(self, *args, **kwargs):
        kwargs["multiple"] = True
        super().__init__(*args, **kwargs)


class MultiValueCommand(click.Command):
    """A command that rewrites ``--opt a b c`` into ``--opt a --opt b --opt c`` for
    :class:`MultiValueOption` options before click parses the arguments.

    Values are taken until the next token that starts with ``-``; positional arguments must
    therefore come before such an option.
    """

    def parse_args(self, ctx, args):
        flags = {o for p in self.params if isinstance(p, MultiValueOption) for o in p.opts}
        out, current, fresh = [], None, False
        for a in args:
            if a.startswith("-") and a != "-":
                current = a if a in flags else None
                fresh = current is not None
                out.append(a)
                continue
            if current is not None and not fresh:
                out.append(current)
            fresh = False
            out.append(a)
        return super().parse_args(ctx, out)


_FILE = click.Path(exists=True, dir_okay=False, path_type=Path)
_OUT = click.Path(dir_okay=False, path_type=Path)
_DIR = click.Path(file_okay=False, path_type=Path)


@click.command("select")
@click.argument("pulses", type=_FILE)
@click.option("--fields", type=_FILE, required=True, help="fields.csv of the campaign folder.")
@click.option("--datasets", type=_FILE, required=True, help="datasets.csv of the campaign folder.")
@click.option("--out", type=_OUT, required=True, help="Output Parquet: the selected pulses.")
@stage_options
def select(pulses, fields, datasets, out, cfg):
    """Select the pulses whose first echo hits a field sample (METHOD.md i1, i4).

    PULSES is the AGC-normalised pulse table of one dataset (results/agc/{dataset}.parquet).
    Adds sample_id, species, functional_group, ground_z, height_m and the flags
    classification_set (single DR echo, species with >= select.min_pulses pulses) and
    comparison_set (modelled species, birch 2.5-5 m), and below_crown_set: pulses under a
    comparison tree's crown whose first echo is lower than select.tree_min_echo_h_m (for
    diagnose only).
    """
    from .select import run

    s = run(pulses, fields, datasets, out, cfg)
    click.echo(f"select: {s.dataset}: {s.n_selected} of {s.n_pulses} pulses on {s.n_samples} samples "
               f"({s.n_classification} classification, {s.n_comparison} comparison, {s.n_below_crown} below crown) "
               f"-> {out}")


@click.command("simulate")
@click.argument("selected", type=_FILE)
@click.option("--fields", type=_FILE, default=None,
              help="fields.csv: sample positions and heights when the select table lacks them.")
@click.option("--datasets", type=_FILE, required=True, help="datasets.csv of the campaign folder.")
@click.option("--system", type=_FILE, required=True, help="Calibrated S(t) of the dataset (Parquet).")
@click.option("--calibration", type=_FILE, required=True, help="Calibration JSON (noise_mean, noise_sd).")
@click.option("--chunk", type=int, default=0, show_default=True, help="Chunk index, 0 .. chunks-1.")
@click.option("--chunks", type=int, default=None, help="Number of chunks (default simulate.chunks).")
@click.option("--effect", "effects", multiple=True, metavar="NAME=VALUE",
              help="Add an effect to the model (src/waveforest/effects.py); repeatable. Overrides simulate.effects.")
@click.option("--out", type=_OUT, required=True, help="Output Parquet: the simulated pulse table (source = sim).")
@stage_options
def simulate(selected, fields, datasets, system, calibration, chunk, chunks, effects, out, cfg):
    """Simulate the selected pulses of the modelled species: vegetation instance, MCRT, sensor.

    SELECTED is the dataset's select table. The pulses of field samples assigned to chunk
    CHUNK (a stable hash of the sample and its vegetation instance) are simulated with the
    real pulse geometry, the dataset's S(t) and noise, and written with source = sim and
    the real pulse_id.
    """
    from ..effects import parse_effects
    from .simulate import run

    eff = dict(cfg["simulate"]["effects"])
    eff.update(parse_effects(list(effects)))
    n_chunks = cfg["simulate"]["chunks"] if chunks is None else chunks
    s = run(selected, datasets, system, calibration, out, cfg, chunk=chunk, chunks=n_chunks, effects=eff,
            fields_path=fields)
    click.echo(f"simulate: {s.dataset} chunk {chunk}/{n_chunks}: {s.n_written} of {s.n_pulses} pulses "
               f"({s.n_instances} vegetation instances, {s.n_no_echo} without echo) -> {out}")


@click.command("compare", cls=MultiValueCommand)
@click.option("--real", "real", cls=MultiValueOption, type=_FILE, required=True,
              help="Feature tables of the selected real pulses (one or more).")
@click.option("--sim", "sim", cls=MultiValueOption, type=_FILE, required=True,
              help="Feature tables of the simulated pulses (one or more).")
@click.option("--pulses-real", "pulses_real", cls=MultiValueOption, type=_FILE,
              help="select tables (comparison flags and real waveforms).")
@click.option("--pulses-sim", "pulses_sim", cls=MultiValueOption, type=_FILE,
              help="simulate chunk tables (simulated waveforms).")
@click.option("--out", type=_DIR, required=True, help="Output folder (table3.csv, table3.md, fig6_*, fig7_*).")
@stage_options
def compare(real, sim, pulses_real, pulses_sim, out, cfg):
    """Real vs simulated features: the Table 3 analogue and Figures 6-7 (METHOD.md i1)."""
    from .compare import run

    r = run(real, sim, pulses_real, pulses_sim, out, cfg)
    click.echo(f"compare: {r.table_csv}, {r.table_md}, {r.order_csv} and {len(r.figures)} figures")


@click.command("sensitivity")
@click.option("--system", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="S(t) of 2010_12_1 (Parquet); omitted = Gaussian of "
                   "sensitivity.reference_system.fwhm_ns.")
@click.option("--calibration", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Calibration JSON with noise_mean/noise_sd (default: beside --system).")
@click.option("--out", type=_DIR, required=True, help="Output folder (sensitivity.csv, fig8.png).")
@stage_options
def sensitivity(system, calibration, out, cfg):
    """Sensitivity of simulated birch Apeak to leaf angle, rho, tau and leaf area (METHOD.md i2)."""
    from .sensitivity import run

    r = run(out, cfg, system_path=system, calibration_path=calibration)
    click.echo(f"sensitivity: {r.n_settings} settings x {r.pulses} pulses -> {r.table}, {r.figure}")


@click.command("sensor-study")
@click.option("--system", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="S(t) of 2010_12_1 (Parquet); omitted = Gaussian of "
                   "sensitivity.reference_system.fwhm_ns.")
@click.option("--calibration", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Calibration JSON with noise_mean/noise_sd (default: beside --system).")
@click.option("--out", type=_DIR, required=True, help="Output folder (sensor_study.csv, fig9.png).")
@stage_options
def sensor_study(system, calibration, out, cfg):
    """Divergence, pulse width and sampling vs three-species LDA accuracy (METHOD.md i3)."""
    from .sensor_study import run

    r = run(out, cfg, system_path=system, calibration_path=calibration)
    click.echo(f"sensor-study: {r.n_settings} settings, {r.n_pulses} simulated pulses -> {r.table}, {r.figure}")


@click.command("classify", cls=MultiValueCommand)
@click.argument("features", type=_FILE)
@click.option("--select", "select_paths", cls=MultiValueOption, type=_FILE,
              help="The dataset's select table, to add flags a feature table lacks (optional).")
@click.option("--out", type=_OUT, required=True, help="Output JSON.")
@stage_options
def classify(features, select_paths, out, cfg):
    """LDA of four functional groups on one dataset's real pulses (METHOD.md i4, Table 4).

    FEATURES is the feature table of the dataset's selected real pulses.
    """
    from .classify import run

    r = run(features, out, cfg, select_paths=select_paths)
    one = r["main"].get("one_pulse") or {}
    acc = (one.get("resubstitution") or {}).get("accuracy", float("nan"))
    click.echo(f"classify: {r['dataset']}: {r['n_pulses']} pulses, {r['n_samples']} samples, "
               f"1-pulse accuracy {100 * acc:.1f} % -> {out}")
