"""The ``diagnose`` stage: gap, search, the extended model, "after" and the outputs.

Inputs (per diagnosed dataset): the ``select`` table (pulse geometry and sample columns),
the real feature table (``features``), the calibration (S(t) Parquet and JSON), the
AGC-normalised pulse table (``agc``: its calibration-target pulses, to recalibrate S(t) under
the candidates ``nonlinearity`` and ``trigger_loss``), and the campaign's datasets.csv and
targets.csv. Steps:

1. **Pulses.** The comparison pulses of the modelled species (``select``'s
   ``comparison_set``, ``simulate.species``) of ``diagnose.datasets`` (default: the
   comparison datasets), and their real features, with ``compare``'s rules
   (:func:`.simulator.apply_rules`); with ``diagnose.below_crown``, also, as a stratum of
   their own (``stratum`` :data:`.simulator.BELOW_CROWN`), the pulses whose own first CFD
   echo lies under a comparison tree's crown (:func:`with_pulses_under_crowns`): the ground
   seen through gaps in the crown, where vegetation under the trees shows. Candidates are fitted on at most
   ``diagnose.fit_pulses`` of them per dataset x species x stratum (a seeded hash order, so
   the subset does not depend on the order of the files) and tested on all.
2. **Search** (:func:`.search.search`) with the study's simulation chain
   (:class:`.simulator.StudySimulator`) on top of ``simulate.effects`` (the base model).
3. **After.** All pulses are simulated again with a fresh seed, independent of the search,
   under the base model and under the extended model (base + named effects); the gap of
   each against the real data, per cell, per feature and in total, with a paired cluster
   bootstrap (:func:`.gap.before_after`). Nothing named: "after" is the base model.
4. **Signatures.** Each candidate at the grid value nearest its realistic test value
   (:mod:`waveforest.effects`) against the base model, same seed (from the search's
   simulation cache: no extra simulation when round 1 ran): how it moves each feature.
5. **Outputs** in ``out_dir``: ``model.yaml``, ``candidates.csv``,
   ``gap_before_after.csv``, ``gap.png``, ``signatures.csv``, ``diagnose.md``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from waveforest.atomic import atomic_path
from waveforest.cliutil import (
    EXISTING_DIR,
    EXISTING_FILE,
    OUT_DIR,
    MultiValueCommand,
    MultiValueOption,
    stage_options,
)
from waveforest.diagnose import catalogue as cat
from waveforest.diagnose import gap as _gap
from waveforest.diagnose.figures import gap_figure
from waveforest.diagnose.model import model_dict, write_model
from waveforest.diagnose.search import SearchResult, SearchSettings, search
from waveforest.diagnose.simulator import BELOW_CROWN, StudySimulator, apply_rules, own_cfd_echoes
from waveforest.effects import CATALOGUE
from waveforest.errors import WaveforestError
from waveforest.io.pulses import read_pulses
from waveforest.io.tables import dataset_row, read_datasets, read_fields, read_targets
from waveforest.model.forward import hash_ids, stable_hash
from waveforest.sensor import FeatureParams, feature_table
from waveforest.sensor import load_calibration as load_json
from waveforest.sensor.calibration import CALIBRATION_EFFECTS
from waveforest.stages.agc import read_agc_metadata
from waveforest.stages.calibrate import read_calibration_pulses
from waveforest.stages.classify import read_feature_tables
from waveforest.stages.select import SelectRules, dataset_of, select_pulses
from waveforest.stages.simulate import load_calibration, with_sample_columns

KEY_COLUMNS = ("dataset", "pulse_id", "sample_id", "species", "is_tree", "comparison_set", "below_crown_set")
"""``select`` columns that identify a pulse to simulate."""

OUTPUT_NAMES = {
    "model": "model.yaml",
    "candidates": "candidates.csv",
    "gap": "gap_before_after.csv",
    "figure": "gap.png",
    "signatures": "signatures.csv",
    "markdown": "diagnose.md",
}
"""Files written by :func:`run` (keys of :class:`DiagnoseOutputs`)."""


@dataclass
class DiagnoseOutputs:
    """What :func:`run` wrote and found."""

    paths: dict
    verdict: str
    effects: dict
    gap_before: float
    gap_after: float
    n_pulses: int
    n_samples: int
    n_simulations: int
    seconds: float


def diagnosed_datasets(cfg: dict) -> list[str]:
    """``diagnose.datasets``, default the comparison datasets that are processed."""
    chosen = cfg["diagnose"]["datasets"]
    if chosen is None:
        chosen = [d for d in cfg["simulate"]["datasets"] if d in cfg["datasets"]]
    return [str(d) for d in chosen]


def pulse_keys(selected: dict, cfg: dict, cap: int | None = None) -> pd.DataFrame:
    """The pulses the diagnosis simulates (step 1 of the module docstring).

    Parameters
    ----------
    selected : dict
        Dataset -> ``select`` pa.Table.
    cfg : dict
        Loaded study config.
    cap : int, optional
        At most this many pulses per dataset x species x stratum (a seeded random subset: a
        smaller cap gives a subset of a larger one); None = all.

    Returns
    -------
    DataFrame
        dataset, pulse_id, sample_id, species, is_tree, stratum (:data:`.simulator.BELOW_CROWN` or "");
        sorted by dataset and pulse_id.
    """

    species = [str(s) for s in cfg["simulate"]["species"]]
    optional = ("is_tree", "below_crown_set")  # select tables of other tools may lack them
    parts = []
    for ds, table in sorted(selected.items()):
        missing = [c for c in KEY_COLUMNS if c not in table.column_names and c not in optional]
        if missing:
            raise WaveforestError(f"select table of {ds} lacks column(s) {', '.join(missing)}")
        df = table.select([c for c in KEY_COLUMNS if c in table.column_names]).to_pandas()
        df = df.reindex(columns=list(KEY_COLUMNS), fill_value=False)
        below = df["below_crown_set"].fillna(False).astype(bool) & bool(cfg["diagnose"]["below_crown"])
        df = df[(df["comparison_set"].fillna(False).astype(bool) | below) & df["species"].astype(str).isin(species)]
        df = df.assign(stratum=np.where(below[df.index], BELOW_CROWN, "")).drop(
            columns=["comparison_set", "below_crown_set"])
        if cap is not None:
            rank = hash_ids(stable_hash(int(cfg["seed"]), ds, "diagnose"), df["pulse_id"].to_numpy(np.int64))
            df = df.assign(_rank=rank).sort_values(["_rank", "pulse_id"])
            df = df.groupby(["species", "stratum"], sort=False).head(int(cap)).drop(columns="_rank")
        parts.append(df)
    keys = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(
        columns=["dataset", "pulse_id", "sample_id", "species", "is_tree", "stratum"])
    keys["sample_id"] = keys["sample_id"].astype(str)
    keys["species"] = keys["species"].astype(str)
    keys["dataset"] = keys["dataset"].astype(str)
    return keys.sort_values(["dataset", "pulse_id"]).reset_index(drop=True)


def real_features(features: pd.DataFrame, keys: pd.DataFrame, cfg: dict) -> pd.DataFrame:
    """The real feature rows of ``keys``' pulses, with ``compare``'s rules applied."""

    f = features.copy()
    if "source" in f.columns:
        f = f[f["source"].astype(str) == "real"]
    f["dataset"] = f["dataset"].astype(str)
    key_cols = ["dataset", "pulse_id", "sample_id", "species", "is_tree", "stratum"]
    f = f.drop(columns=[c for c in key_cols[2:] if c in f.columns])
    real = keys[key_cols].merge(f, on=["dataset", "pulse_id"], how="inner", validate="one_to_one")
    if real.empty:
        raise WaveforestError("diagnose: no real feature row matches the selected comparison pulses")
    return apply_rules(real, cfg)


def with_pulses_under_crowns(selected: pa.Table, agc: pa.Table, fields: pd.DataFrame, year: int, calibration,
                             cfg: dict) -> pa.Table:
    """``selected`` with its ``below_crown_set`` re-drawn by the pulses' own first CFD echo.

    The real side of the stratum "below crown" is chosen by the detector that chooses its twins
    (:mod:`.simulator`): every pulse of the dataset gets the CFD echoes of its own waveform
    (:func:`.simulator.own_cfd_echoes`), and ``select``'s rules
    (:func:`waveforest.stages.select.select_pulses`) on those echoes say which lie under a
    compared crown. Those rows carry their CFD echoes and replace the pulses' ``select`` rows,
    also those of a crown the DR echo gave them (a DR that fired on a weak crown return the
    CFD passes over: 4 and 22 of the 2012 dataset's 58 and 193 such pulses, on a birch campaign
    without effects and with a hidden xy_error 0.25; its twin is sorted by the CFD too).

    Parameters
    ----------
    selected : pa.Table
        ``select`` table of one dataset.
    agc : pa.Table
        Its AGC-normalised pulse table (``agc`` stage).
    fields : DataFrame
        fields.csv.
    year : int
        The dataset's campaign year.
    calibration : waveforest.stages.simulate.Calibration
    cfg : dict
        Loaded study config.
    """

    own = select_pulses(own_cfd_echoes(agc, calibration, cfg), fields, year, SelectRules.from_config(cfg))
    under = own.filter(own.column("below_crown_set"))
    keep = pc.invert(pc.is_in(selected.column("pulse_id"), value_set=under.column("pulse_id")))
    if "below_crown_set" in selected.column_names:
        keep = pc.and_(keep, pc.invert(pc.fill_null(selected.column("below_crown_set"), False)))
    ordinary = selected.filter(keep)
    under = under.select([c for c in ordinary.column_names if c in under.column_names])
    return pa.concat_tables([ordinary, under], promote_options="permissive")


def below_crown_features(keys: pd.DataFrame, selected: dict, metas: dict, cfg: dict) -> pd.DataFrame:
    """Real feature rows of the stratum "below crown" of ``keys``, from their own CFD echoes
    (:func:`with_pulses_under_crowns`), with ``compare``'s rules.

    Parameters
    ----------
    keys : DataFrame
        :func:`pulse_keys`.
    selected : dict
        Dataset -> table of :func:`with_pulses_under_crowns`.
    metas : dict
        Dataset -> calibration JSON dict.
    cfg : dict
        Loaded study config.
    """

    below = keys[keys["stratum"] == BELOW_CROWN]
    parts = []
    for ds, rows in below.groupby("dataset", sort=True):
        table = selected[ds]
        sub = table.filter(pc.is_in(table.column("pulse_id"), value_set=pa.array(rows["pulse_id"].to_numpy(np.int64))))
        parts.append(feature_table(sub, {ds: metas[ds]}, FeatureParams.from_config(cfg)))
    return real_features(pd.concat(parts, ignore_index=True), below, cfg) if parts else pd.DataFrame()


def signatures(result: SearchResult, settings: SearchSettings) -> pd.DataFrame:
    """How each candidate at (the grid value nearest) its test value moves the features.

    Against the base model with the same seed (common random numbers), both halves.

    Returns
    -------
    DataFrame
        effect, value, test_value and the columns of :func:`.catalogue.signature`.
    """
    sims = result.simulations
    if sims is None:
        return pd.DataFrame()
    off = sims.all({})
    parts = []
    for name in settings.candidates:
        u_grid = cat.grid(name, settings.values)
        u = float(u_grid[np.argmin(np.abs(u_grid - cat.to_u(name, CATALOGUE[name].test_value)))])
        if abs(u - cat.off_u(name)) < 1e-12:
            continue
        value = cat.from_u(name, u)
        on = sims.all(cat.with_effect({}, name, value))
        try:
            sig = cat.signature(off, on, features=settings.features, floors=settings.floors,
                                min_pulses=settings.min_pulses, min_samples=1)
        except WaveforestError:
            continue
        sig.insert(0, "test_value", CATALOGUE[name].test_value)
        sig.insert(0, "value", value)
        sig.insert(0, "effect", name)
        parts.append(sig)
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()


def _simulate_all(simulate, keys: pd.DataFrame, effects: dict, seed: int, replicates: int) -> pd.DataFrame:
    parts = []
    for r in range(replicates):
        s = int(np.random.SeedSequence([seed, r]).generate_state(1)[0])
        parts.append(simulate(keys.assign(replicate=r), dict(effects), s))
    return pd.concat(parts, ignore_index=True)


def find_missing_effects(keys: pd.DataFrame, real: pd.DataFrame, simulate, settings: SearchSettings, seed: int, *,
             progress=None, fit_keys: pd.DataFrame | None = None
             ) -> tuple[SearchResult, pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Search (fits on ``fit_keys``, default all), re-simulate ``keys`` before/after with a
    fresh seed, signatures (no file output).

    Returns
    -------
    result : SearchResult
    gap : DataFrame
        :func:`.gap.before_after` of the fresh simulations.
    candidates : DataFrame
        The ranked evidence with a ``named`` column (the winner of each round).
    sigs : DataFrame
        :func:`signatures`.
    """
    s_search, s_after, s_boot = np.random.SeedSequence([int(seed), 8]).generate_state(3)
    result = search(keys, real, simulate, settings, seed=int(s_search), progress=progress, fit_keys=fit_keys)
    before = _simulate_all(simulate, keys, {}, int(s_after), settings.replicates)
    after = before if not result.named else _simulate_all(simulate, keys, result.effects, int(s_after),
                                                          settings.replicates)
    gap = _gap.before_after(real, before, after, n_boot=settings.n_boot, seed=int(s_boot), alpha=settings.alpha,
                            **settings.gap_kw)
    cand = result.candidates.copy()
    if not cand.empty:
        winners = {(e.round, e.name) for e in result.named}
        cand["named"] = [(r, n) in winners for r, n in zip(cand["round"], cand["name"])]
        cand = cand.sort_values(["round", "rank"]).reset_index(drop=True)
    else:
        cand = pd.DataFrame(columns=["round", "rank", "name", "value", "ci_low", "ci_high", "gap_base", "gap_new",
                                     "gap_reduction", "reduction_ci_low", "reduction_ci_high",
                                     "relative_reduction", "significant", "at_bound", "vs_best_ci_low",
                                     "vs_best_ci_high", "named"])
    lead = ["round", "rank", "name", "value", "ci_low", "ci_high", "gap_reduction", "reduction_ci_low",
            "reduction_ci_high", "relative_reduction", "significant", "at_bound", "named"]
    cand = cand[lead + [c for c in cand.columns if c not in lead]]
    return result, gap, cand, signatures(result, settings)


def _fmt(x: float, nd: int = 3) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if isinstance(x, float) and math.isinf(x):
        return "inf"
    return f"{x:.{nd}g}"


def summary_markdown(result: SearchResult, gap: pd.DataFrame, cand: pd.DataFrame, *, datasets, n_pulses: int,
                     n_samples: int, seconds: float, settings: SearchSettings, base_effects: dict,
                     n_fit_pulses: int | None = None) -> str:
    """A short human summary (``diagnose.md``)."""
    tot = gap[gap["level"] == "total"].iloc[0]
    lines = [
        "# Diagnosis: where simulation and measurement disagree",
        "",
        f"**Verdict: {result.verdict}.** {result.reason}.",
        "",
        f"Datasets {', '.join(datasets)}; {n_pulses} real pulses from {n_samples} field samples; "
        f"base model effects {base_effects or 'none (the paper model)'}; {result.n_simulations} half-sample "
        f"simulations in the search ({settings.replicates} simulated pulse(s) per real pulse and value; "
        f"candidates fitted on {n_fit_pulses if n_fit_pulses is not None else n_pulses} pulses, tested on all); "
        f"{seconds:.0f} s.",
        "",
        "The gap is the mean over dataset x species x feature cells of d^2 + ln(SD ratio)^2 (d = mean "
        "difference in pooled SDs; src/waveforest/diagnose/gap.py); the noise floor is the gap that "
        "sampling noise alone gives (cluster bootstrap over field samples). With diagnose.below_crown, "
        "a tree species' pulses whose first echo lies lower than select.tree_min_echo_h_m, the ground "
        "seen through gaps in its crowns, form the cells '<species> below crown'.",
        "",
        f"- base model: gap {_fmt(tot['gap_before'])} [{_fmt(tot['before_ci_low'])}, "
        f"{_fmt(tot['before_ci_high'])}], noise floor {_fmt(tot['noise_floor'])}",
        f"- extended model: gap {_fmt(tot['gap_after'])} [{_fmt(tot['after_ci_low'])}, "
        f"{_fmt(tot['after_ci_high'])}]",
        f"- reduction {_fmt(tot['reduction'])} [{_fmt(tot['reduction_ci_low'])}, "
        f"{_fmt(tot['reduction_ci_high'])}] (fresh simulations, independent of the search)",
        "",
    ]
    if result.named:
        lines += ["## Named effects", "", "| effect | value | 95 % interval | round | test-half gap reduction |",
                  "|---|---|---|---|---|"]
        for e in result.named:
            lines.append(f"| {e.name} | {_fmt(e.value)} | [{_fmt(e.ci_low)}, {_fmt(e.ci_high)}] | {e.round} | "
                         f"{_fmt(e.gap_reduction)} [{_fmt(e.reduction_ci_low)}, {_fmt(e.reduction_ci_high)}] |")
        lines.append("")
        for e in result.named:
            if e.look_alikes:
                lines += [f"{', '.join(e.look_alikes)} reduced the gap significantly too in round {e.round}, by an "
                          f"amount not told apart from {e.name}'s: on these data, as good an explanation.", ""]
        model = {**base_effects, **result.effects}
        lines += [f"Use it: `simulate: {{effects: {{{', '.join(f'{k}: {v:.4g}' for k, v in model.items())}}}}}`.",
                  ""]
    if not cand.empty:
        lines += ["## Candidates (best three per round)", "",
                  "| round | rank | effect | value | gap reduction [95 %] | relative | significant |",
                  "|---|---|---|---|---|---|---|"]
        for _, r in cand[cand["rank"] <= 3].iterrows():
            lines.append(f"| {r['round']} | {r['rank']} | {r['name']} | {_fmt(r['value'])} | "
                         f"{_fmt(r['gap_reduction'])} [{_fmt(r['reduction_ci_low'])}, "
                         f"{_fmt(r['reduction_ci_high'])}] | {_fmt(r['relative_reduction'], 2)} | "
                         f"{'yes' if r['significant'] else 'no'}{' (fit at a bound)' if r['at_bound'] else ''} |")
        lines.append("")
    lines += ["Files: model.yaml (the extended model), candidates.csv (all candidates, ranked), "
              "gap_before_after.csv (per cell, feature and total), gap.png, signatures.csv (how each "
              "candidate moves the features), this summary.", ""]
    return "\n".join(lines)


def write_outputs(out_dir, result: SearchResult, gap: pd.DataFrame, cand: pd.DataFrame, sigs: pd.DataFrame, *,
                  settings: SearchSettings, base_effects: dict, datasets, keys: pd.DataFrame,
                  seconds: float, n_fit_pulses: int | None = None) -> dict:
    """Write the six outputs of :data:`OUTPUT_NAMES` into ``out_dir`` (atomically); returns their paths."""
    out_dir = Path(out_dir)
    base = dict(base_effects)
    tot = gap[gap["level"] == "total"].iloc[0]
    paths = {k: out_dir / v for k, v in OUTPUT_NAMES.items()}
    model = model_dict(
        result.verdict, result.named, reason=result.reason, base_effects=base,
        gap={"before": float(tot["gap_before"]), "before_ci": [float(tot["before_ci_low"]),
                                                               float(tot["before_ci_high"])],
             "after": float(tot["gap_after"]), "after_ci": [float(tot["after_ci_low"]), float(tot["after_ci_high"])],
             "noise_floor": float(tot["noise_floor"]), "reduction": float(tot["reduction"]),
             "reduction_ci": [float(tot["reduction_ci_low"]), float(tot["reduction_ci_high"])]},
        extra={"datasets": list(datasets), "n_pulses": int(len(keys)),
               "n_fit_pulses": int(len(keys) if n_fit_pulses is None else n_fit_pulses),
               "n_samples": int(keys["sample_id"].nunique()), "search_simulations": int(result.n_simulations),
               "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(settings).items()
                            if k not in ("floors",)}},
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    write_model(paths["model"], model)
    for key, table in (("candidates", cand), ("gap", gap), ("signatures", sigs)):
        with atomic_path(paths[key]) as tmp:
            table.to_csv(tmp, index=False, float_format="%.6g")

    named = ", ".join(f"{e.name} = {e.value:.3g}" for e in result.named)
    gap_figure(gap, cand, paths["figure"], title=f"verdict: {result.verdict}" + (f" ({named})" if named else ""))
    md = summary_markdown(result, gap, cand, datasets=list(datasets), n_pulses=len(keys),
                          n_samples=int(keys["sample_id"].nunique()), seconds=seconds, settings=settings,
                          base_effects=base, n_fit_pulses=n_fit_pulses)
    with atomic_path(paths["markdown"]) as tmp:
        tmp.write_text(md)
    return paths


def _calibration_pulses(agc_paths, targets_path, datasets_path, selected: dict, settings: SearchSettings,
                        cfg: dict) -> dict:
    """Dataset -> calibration-target pulses, read only when a calibration-shaping candidate is tried."""

    if not agc_paths or not set(CALIBRATION_EFFECTS) & set(settings.candidates):
        return {}
    if targets_path is None:
        raise WaveforestError("diagnose: AGC-normalised pulse tables given without targets.csv")
    targets, datasets = read_targets(targets_path), read_datasets(datasets_path)
    paths = _agc_by_dataset(agc_paths)
    return {ds: read_calibration_pulses(paths[ds], targets, datasets, cfg) for ds in selected if ds in paths}


def _with_pulses_under_crowns(selected: dict, agc_paths, fields, datasets_path, calibrations: dict, cfg: dict) -> dict:
    """:func:`with_pulses_under_crowns` of every diagnosed dataset (``diagnose.below_crown``)."""

    if not agc_paths or fields is None:
        raise WaveforestError("diagnose.below_crown: the AGC-normalised pulse tables (--agc) and fields.csv are "
                              "needed to find the pulses under the crowns")
    paths = _agc_by_dataset(agc_paths)
    missing = sorted(set(selected) - set(paths))
    if missing:
        raise WaveforestError(f"diagnose.below_crown: no AGC-normalised pulse table of {', '.join(missing)}")
    datasets = read_datasets(datasets_path)
    return {ds: with_pulses_under_crowns(table, read_pulses(paths[ds]), fields,
                                         int(dataset_row(datasets, ds, datasets_path)["year"]), calibrations[ds][0],
                                         cfg) for ds, table in selected.items()}


def _agc_by_dataset(agc_paths) -> dict:
    """Dataset -> path of its AGC-normalised pulse table (the dataset named in its metadata)."""

    return _by_dataset(agc_paths, lambda p: (str(read_agc_metadata(p).get("dataset", p.stem)), p),
                       "AGC-normalised pulse table")


def _by_dataset(paths, reader, what: str) -> dict:
    out = {}
    for p in paths:
        name, value = reader(Path(p))
        if name in out:
            raise WaveforestError(f"{p}: a second {what} for dataset {name}")
        out[name] = value
    return out


def run(selected_paths, real_paths, calibration_paths, out_dir, cfg: dict, *, datasets_path,
        system_paths=None, fields_path=None, agc_paths=None, targets_path=None, simulator=None,
        progress: bool = True) -> DiagnoseOutputs:
    """The ``diagnose`` stage (module docstring).

    Parameters
    ----------
    selected_paths : paths
        ``select`` tables (``results/select/{dataset}.parquet``).
    real_paths : paths
        Real feature tables (``results/features/{dataset}_real.parquet``).
    calibration_paths : paths
        Calibration JSONs (``results/calibration/{dataset}.json``).
    out_dir : path
        Output folder (``results/diagnose``).
    cfg : dict
        Loaded study config (sections diagnose, simulate, mcrt, vegetation, sensor, seed).
    datasets_path : path
        The campaign's datasets.csv.
    system_paths : paths, optional
        S(t) Parquet files (``results/calibration/{dataset}.parquet``); default: beside each
        calibration JSON, same stem.
    fields_path : path, optional
        fields.csv, for select tables that lack sample_x, sample_y, height_m.
    agc_paths, targets_path : paths, path, optional
        AGC-normalised pulse tables (``results/agc/{dataset}.parquet``) and targets.csv: the
        calibration-target pulses, so that the candidates ``nonlinearity`` and ``trigger_loss``
        are tried with S(t) recalibrated under each value (:mod:`.simulator`); without them,
        on top of the calibrated S(t).
    simulator : callable, optional
        ``simulate(pulses, effects, seed)`` instead of the study chain (tests).
    progress : bool
        tqdm bar over the simulations (stderr).
    """

    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    settings = SearchSettings.from_config(cfg)
    base = dict(cfg["simulate"]["effects"] or {})
    if base:
        settings = replace(settings, candidates=tuple(c for c in settings.candidates if c not in base))
    wanted = diagnosed_datasets(cfg)
    fields = read_fields(fields_path) if fields_path is not None else None

    def read_select(p):
        t = read_pulses(p)
        if fields is not None:
            t = with_sample_columns(t, fields, str(fields_path))
        return dataset_of(t, str(p)), t

    selected = {k: v for k, v in _by_dataset(selected_paths, read_select, "select table").items() if k in wanted}
    if not selected:
        raise WaveforestError(f"diagnose: no select table of the diagnosed datasets {', '.join(wanted)}")
    metas = _by_dataset(calibration_paths, lambda p: (str(load_json(p)["dataset"]), p), "calibration")
    systems = {}
    for ds in selected:
        if ds not in metas:
            raise WaveforestError(f"diagnose: no calibration JSON for dataset {ds}")
        systems[ds] = Path(metas[ds]).with_suffix(".parquet")
    for p in system_paths or ():
        if Path(p).stem in systems:
            systems[Path(p).stem] = Path(p)
    under_crowns = bool(cfg["diagnose"]["below_crown"])
    calibrations = {}
    if simulator is None or under_crowns:
        for ds in selected:
            if not systems[ds].exists():
                raise WaveforestError(f"{systems[ds]}: no such S(t) file (calibration of {ds})")
            calibrations[ds] = (load_calibration(systems[ds], metas[ds]), load_json(metas[ds]))
    if under_crowns:
        selected = _with_pulses_under_crowns(selected, agc_paths, fields, datasets_path, calibrations, cfg)
    keys = pulse_keys(selected, cfg)
    fit_cap = cfg["diagnose"]["fit_pulses"]
    fit_keys = None if fit_cap is None else pulse_keys(selected, cfg, int(fit_cap))
    if keys.empty:
        raise WaveforestError("diagnose: no comparison pulse of the modelled species in the select tables")
    real = real_features(read_feature_tables(real_paths), keys[keys["stratum"] != BELOW_CROWN], cfg)
    if under_crowns:
        below = below_crown_features(keys, selected, {ds: meta for ds, (_, meta) in calibrations.items()}, cfg)
        real = pd.concat([real, below], ignore_index=True)
    if simulator is None:
        use_rc = bool(cfg["sensor"]["cfd"]["range_correction"])
        simulator = StudySimulator(selected, read_datasets(datasets_path), calibrations, cfg, base_effects=base,
                                   range_correction=use_rc,
                                   calibration_pulses=_calibration_pulses(agc_paths, targets_path, datasets_path,
                                                                          selected, settings, cfg))
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(desc="diagnose: simulations", unit="sim")
    result, gap, cand, sigs = find_missing_effects(keys, real, simulator, settings, int(cfg["seed"]), fit_keys=fit_keys,
                                       progress=(lambda label: bar.update(1)) if bar is not None else None)
    if bar is not None:
        bar.close()
    seconds = time.perf_counter() - t_start
    paths = write_outputs(out_dir, result, gap, cand, sigs, settings=settings, base_effects=base,
                          datasets=sorted(selected), keys=keys, seconds=seconds,
                          n_fit_pulses=None if fit_keys is None else len(fit_keys))
    tot = gap[gap["level"] == "total"].iloc[0]
    return DiagnoseOutputs(paths=paths, verdict=result.verdict, effects=result.effects,
                           gap_before=float(tot["gap_before"]), gap_after=float(tot["gap_after"]),
                           n_pulses=int(len(keys)), n_samples=int(keys["sample_id"].nunique()),
                           n_simulations=int(result.n_simulations), seconds=time.perf_counter() - t_start)


@click.command("diagnose", cls=MultiValueCommand)
@click.option("--selected", "selected", cls=MultiValueOption, type=EXISTING_FILE, required=True,
              help="select tables of the diagnosed datasets (results/select/{dataset}.parquet).")
@click.option("--features-real", "features_real", cls=MultiValueOption, type=EXISTING_FILE, required=True,
              help="Real feature tables (results/features/{dataset}_real.parquet).")
@click.option("--calibration", "calibration", cls=MultiValueOption, type=EXISTING_FILE, required=True,
              help="Calibration JSONs (results/calibration/{dataset}.json).")
@click.option("--system", "system", cls=MultiValueOption, type=EXISTING_FILE,
              help="S(t) Parquet files (results/calibration/{dataset}.parquet); default: beside each JSON.")
@click.option("--agc", "agc", cls=MultiValueOption, type=EXISTING_FILE,
              help="AGC-normalised pulse tables (results/agc/{dataset}.parquet): their calibration-target "
                   "pulses recalibrate S(t) under each value of the candidates nonlinearity and trigger_loss; "
                   "without them those candidates act on top of the calibrated S(t).")
@click.option("--campaign", "campaign", type=EXISTING_DIR, required=True,
              help="Campaign folder (its datasets.csv and targets.csv; fields.csv if present).")
@click.option("--out", "out", type=OUT_DIR, required=True,
              help="Output folder: model.yaml, candidates.csv, gap_before_after.csv, gap.png, "
                   "signatures.csv, diagnose.md.")
@stage_options
def diagnose(selected, features_real, calibration, system, agc, campaign, out, cfg):
    """Find where simulation and measurement disagree, name the missing effect, show the gap shrink.

    Beyond the paper: each effect of the catalogue (src/waveforest/effects.py) is fitted on
    one half of the field samples and tested on the other (config section `diagnose`).
    """

    fields = campaign / "fields.csv"
    res = run(list(selected), list(features_real), list(calibration), out, cfg,
              datasets_path=campaign / "datasets.csv", system_paths=list(system or ()),
              fields_path=fields if fields.exists() else None, agc_paths=list(agc or ()),
              targets_path=campaign / "targets.csv")
    named = ", ".join(f"{k} = {v:.3g}" for k, v in res.effects.items()) or "nothing named"
    click.echo(f"diagnose: verdict {res.verdict} ({named}); gap {res.gap_before:.3g} -> {res.gap_after:.3g}; "
               f"{res.n_pulses} pulses, {res.n_samples} samples, {res.n_simulations} simulations, "
               f"{res.seconds:.0f} s -> {out}")
