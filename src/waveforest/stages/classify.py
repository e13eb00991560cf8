"""The ``classify`` stage: the Table 4 analogue of one dataset (:mod:`waveforest.analysis.classify`)."""

from __future__ import annotations

import click

from waveforest.analysis.classify import classify_dataset
from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_FILE,
    MultiValueCommand,
    MultiValueOption,
    stage_options,
)
from waveforest.errors import WaveforestError
from waveforest.io.results import (
    SELECT_FLAGS,
    attach_selection,
    read_feature_tables,
    read_select_columns,
    write_classify_result,
)
from waveforest.settings import classify_settings

SELECT_COLUMNS = ["dataset", "pulse_id", "source", "species", "functional_group", "sample_id", "n_echoes", "height_m",
                  *SELECT_FLAGS]
"""Columns classify reads from select tables (those a table has)."""

SELECT_REQUIRED = ("dataset", "pulse_id", "species", "functional_group", "n_echoes")
"""Columns every select table given to classify must have."""


def run(features_path, out_path, cfg: dict, select_paths=()) -> dict:
    """The ``classify`` stage: one dataset's feature table -> JSON (Table 4 row and more).

    ``select_paths`` (optional): the ``select`` tables of every processed dataset. The species
    rule counts over all of them (Table 1); the dataset's own rows add the flags that the
    feature table lacks. Without them the rule counts the feature table's own pulses.
    """
    settings = classify_settings(cfg)
    features = read_feature_tables([features_path])
    selection = None
    if select_paths:
        selection = read_select_columns(select_paths, SELECT_COLUMNS, SELECT_REQUIRED)
        names = set(features["dataset"].astype(str)) if "dataset" in features.columns else set()
        if not names & set(selection["dataset"].astype(str)):
            raise WaveforestError(f"{features_path}: dataset {', '.join(sorted(names)) or '?'} is in none "
                                  f"of the select tables given ({len(select_paths)})")
        features = attach_selection(features, selection[selection["dataset"].astype(str).isin(names)])
    result = classify_dataset(features, settings, selection)
    write_classify_result(result, out_path)
    return result


@click.command("classify", cls=MultiValueCommand)
@click.argument("features", type=EXISTING_FILE)
@click.option("--select", "select_paths", cls=MultiValueOption, type=EXISTING_FILE,
              help="The select tables of every processed dataset: the species rule (>= "
                   "select.min_pulses single-echo pulses) counts over all of them (optional; "
                   "without them it counts FEATURES alone).")
@click.option("--out", type=OUT_FILE, required=True, help="Output JSON.")
@stage_options
def classify(features, select_paths, out, cfg):
    """LDA of four functional groups on one dataset's real pulses (docs/method.md §(i4), Table 4).

    FEATURES is the feature table of the dataset's selected real pulses.

    Example:

    \b
    waveforest classify features_real.parquet --select select.parquet --out classify.json
    """

    r = run(features, out, cfg, select_paths=select_paths)
    one = r["main"].get("one_pulse") or {}
    acc = (one.get("resubstitution") or {}).get("accuracy", float("nan"))
    included = sum(row["included"] for row in r["species_table"])
    click.echo(f"classify: {r['dataset']}: {included} of {len(r['species_table'])} species pass the "
               f"{r['species_rule']['min_pulses']}-pulse rule over {len(r['species_rule']['datasets'])} "
               f"dataset(s); {r['n_pulses']} pulses, {r['n_samples']} samples, "
               f"1-pulse accuracy {100 * acc:.1f} % -> {out}")
    if r["main"].get("dropped_reason"):
        click.echo(f"classify: {r['dataset']}: {r['main']['n_dropped']} pulse(s) left out, "
                   f"{r['main']['dropped_reason']}")
