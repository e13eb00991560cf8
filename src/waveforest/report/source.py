"""The report's opening: what the run ran on, and what its "real" data can show.

- the data source: the virtual campaign (seed and hidden effects from its ``truth.json``, else
  from the config) or the user's campaign folder;
- the config file and every key that differs from the schema's defaults;
- the datasets, and the field-sample and pulse counts beside the paper's, with a plain warning
  where ours are far below (:data:`FAR_BELOW`);
- the code's commit, the input files' SHA-256 and the machine (:mod:`.provenance`);
- :func:`virtual_caveat`: the summary's first sentence when the "real" data are virtual.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.errors import WaveforestError
from waveforest.io import paper
from waveforest.io.results import read_campaign_truth, read_select_columns
from waveforest.report.markdown import format_value
from waveforest.report.provenance import provenance_table
from waveforest.report.summary import ReportSettings, read_csv

FAR_BELOW = 0.1
"""Share of the paper's pulse count below which ours is "far below" (a warning)."""


def campaign_folder(results: Path, settings: ReportSettings) -> Path:
    """The campaign folder of the run: config ``data``, or the virtual one under ``results/campaign``."""
    return Path(settings.data) if settings.data else Path(results) / "campaign"


def campaign_truth(results: Path, settings: ReportSettings) -> dict | None:
    """The campaign's ``truth.json`` (virtual campaigns only); None if absent or unreadable."""
    path = campaign_folder(results, settings) / "truth.json"
    if not path.exists():
        return None
    try:
        return read_campaign_truth(path)
    except WaveforestError:
        return None


def hidden_effects(truth: dict | None, settings: ReportSettings) -> dict:
    """Effects switched on in the virtual campaign, name -> value (``truth.json``, else the config)."""
    if truth is not None:
        return dict(truth.get("active_effects") or {})
    return {k: v for k, v in settings.campaign_effects if v}


def is_virtual(results: Path, settings: ReportSettings) -> bool:
    """True when the "real" data are a virtual campaign (no ``data`` folder, or one holding truth.json)."""
    return settings.data is None or campaign_truth(results, settings) is not None


def _effects_text(effects: dict) -> str:
    return ", ".join(f"{k} = {float(v):g}" for k, v in effects.items()) if effects else "none"


def virtual_caveat(results: Path, settings: ReportSettings) -> str | None:
    """What agreement the virtual "real" data make expected by construction; None for real data."""
    if not is_virtual(results, settings):
        return None
    effects = hidden_effects(campaign_truth(results, settings), settings)
    if not effects:
        return ("**The \"real\" data of this run are virtual**: the campaign was simulated by the same model family "
                "with no hidden effect, so simulated and \"real\" features agree by construction. The Table 3 "
                "differences below measure sampling noise and the differences between campaign and study settings, "
                "not the model's fidelity; Table 4's accuracies measure the virtual vegetation's separability, "
                "not the method's. Neither is a result to set beside the paper's.")
    return (f"**The \"real\" data of this run are virtual**, simulated with the hidden effects "
            f"{_effects_text(effects)}: the differences of Table 3 are expected from those effects (the diagnosis "
            f"should name them); everything else agrees by construction. Table 4's accuracies measure the virtual "
            f"vegetation's separability, not the method's.")


def _setting_text(v) -> str:
    if v is None:
        return "null"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_setting_text(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_setting_text(x)}" for k, x in v.items()) + "}"
    return format(v, "g") if isinstance(v, float) else format_value(v)


def counts(results: Path, settings: ReportSettings) -> tuple[pd.DataFrame | None, pd.DataFrame | None]:
    """Per dataset: field samples and selected pulses (``select/*.parquet``); per dataset and
    species: real pulses compared (``compare/table3.csv``, most over features, as the summary)
    beside the paper's N. Either is None when its source is absent."""
    paths = sorted((Path(results) / "select").glob("*.parquet"))
    per_ds = None
    if paths:
        t = read_select_columns(paths, ("dataset", "sample_id", "classification_set", "comparison_set"), required=())
        if not t.empty:
            g = t.assign(dataset=t["dataset"].astype(str)).groupby("dataset", sort=True)
            per_ds = g.agg(field_samples=("sample_id", "nunique"), selected_pulses=("dataset", "size"),
                           classification_pulses=("classification_set", "sum"),
                           comparison_pulses=("comparison_set", "sum")).reset_index()
    t3 = read_csv(Path(results) / "compare" / "table3.csv")
    per_sp = None
    if t3 is not None and not t3.empty and {"dataset", "species", "n_real"} <= set(t3.columns):
        ours = (t3.assign(dataset=t3["dataset"].astype(str)).groupby(["dataset", "species"], sort=True)["n_real"]
                .max().reset_index(name="real_pulses"))
        pc = paper.table3_counts().assign(dataset=lambda d: d["dataset"].astype(str))
        per_sp = ours.merge(pc.rename(columns={"N": "paper_pulses"}), on=["dataset", "species"], how="left")
        per_sp["share_of_paper_pct"] = 100 * per_sp["real_pulses"] / per_sp["paper_pulses"]
    return per_ds, per_sp


def source_parts(results: str | Path, settings: ReportSettings, config_path: str | None,
                 config_changes=()) -> list[tuple]:
    """The opening section's items: ("text", Markdown) and ("table", caption, DataFrame).

    ``config_changes``: (key path, default, value) of every key that differs from the defaults
    (:func:`waveforest.config.changes`).
    """
    results = Path(results)
    items: list[tuple] = []
    truth = campaign_truth(results, settings)
    folder = campaign_folder(results, settings)
    if settings.data is None or truth is not None:
        seed = truth["seed"] if truth is not None else settings.seed
        whence = (f"seed and effects from `{folder / 'truth.json'}`" if truth is not None
                  else "truth.json not found: seed and effects as the config sets them")
        items.append(("text", f"**Data**: the virtual ALS60 campaign in `{folder}` (`waveforest synthesize`), "
                              f"seed {seed}, hidden effects: {_effects_text(hidden_effects(truth, settings))} "
                              f"({whence}). The \"real\" pulses are simulated."))
    else:
        items.append(("text", f"**Data**: your campaign folder `{folder}`."))
    n = len(config_changes)
    which = f"`{config_path}`" if config_path else "the built-in defaults"
    items.append(("text", f"**Config**: {which}; " + (f"{n} key{'s' if n != 1 else ''} differ from the defaults "
                                                     "(table below; the whole config is at the end of the report)."
                                                     if n else "every key as the defaults.")))
    compared = [d for d in settings.compare_datasets if d in settings.datasets]
    items.append(("text", f"**Datasets**: {', '.join(settings.datasets)}; compared with the simulation "
                          f"(simulate.datasets): {', '.join(compared) if compared else 'none'}. Master seed "
                          f"{settings.seed}."))
    if n:
        items.append(("table", "Config keys that differ from the defaults",
                      pd.DataFrame([(k, _setting_text(d), _setting_text(v)) for k, d, v in config_changes],
                                   columns=["key", "default", "this run"])))
    per_ds, per_sp = counts(results, settings)
    if per_sp is not None:
        share = per_sp["share_of_paper_pct"].to_numpy(float)
        low = per_sp[np.isfinite(share) & (share < 100 * FAR_BELOW)]
        if len(low):
            worst = ", ".join(f"{r.dataset} {r.species} {int(r.real_pulses)} (paper {int(r.paper_pulses):,})"
                              for r in low.itertuples())
            items.append(("text", f"**Warning: far fewer pulses than the paper's** (below {100 * FAR_BELOW:.0f} % "
                                  f"of its N in {len(low)} of {len(per_sp)} dataset-species pairs: {worst}). "
                                  "Differences and accuracies carry sampling errors many times the paper's: this "
                                  "is a smoke- or test-sized run, not a replication."))
    if per_ds is not None:
        items.append(("table", "Field samples and pulses per dataset (select tables)", per_ds))
    if per_sp is not None:
        items.append(("table", "Real pulses compared per dataset and species (compare/table3.csv) beside the "
                               "paper's N", per_sp))
    items.append(("table", "Code, input data and machine: the code and machine that wrote this report (earlier "
                           "steps record the waveforest version only); size and SHA-256 of every campaign file "
                           "the study reads", provenance_table(folder, settings.datasets)))
    return items
