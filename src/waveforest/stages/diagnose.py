"""The ``diagnose`` stage: read the inputs, run the diagnosis, write the outputs.

The science is in :mod:`waveforest.diagnose` (docs/method.md §(j)); this module holds the
click command, :func:`run` and all file I/O. Inputs (per diagnosed dataset): the ``select``
table, the real feature table (``features``), the calibration (S(t) Parquet and JSON), the
AGC-normalised pulse table (``agc``: its calibration-target pulses, to recalibrate S(t)
under the candidates ``nonlinearity`` and ``trigger_loss``; the pulses of the rings around the
trees, :func:`.diagnose.strata.with_ring_pulses`, and with ``diagnose.below_crown`` those under
the crowns, :func:`.diagnose.strata.with_pulses_under_crowns`), and
the campaign's datasets.csv, targets.csv and fields.csv. Steps 1-3 are
:func:`.diagnose.missing_effects.run_diagnosis`, with :func:`waveforest.settings.diagnose_settings`:

1. **Pulses** (:func:`.diagnose.strata.pulse_keys`, :func:`.diagnose.strata.real_features`):
   the comparison pulses of the modelled species of ``diagnose.datasets``, the rings around
   the compared trees (``diagnose.ring_m``) and, with ``diagnose.below_crown``, the stratum
   under the crowns; candidates are fitted on at most
   ``diagnose.fit_pulses`` of them per dataset x species x stratum and tested on all.
2. **Detection limits** (:func:`.diagnose.power.detection_limits`, ``diagnose.power``): the
   smallest value of each candidate that these pulses would detect, with the study's
   simulation chain (:class:`.diagnose.twins.StudySimulator`) on top of
   ``simulate.effects`` (the base model).
3. **Diagnosis** (:func:`.diagnose.missing_effects.find_missing_effects`) with the same
   simulator: search, before/after, signatures (from the search's or step 2's simulations).
4. **Outputs** in ``out_dir`` (:data:`OUTPUT_NAMES`): ``model.yaml``, ``candidates.csv``,
   ``gap_before_after.csv``, ``gap.png``, ``signatures.csv``, ``detection_limits.csv``,
   ``detection_curve.csv``, ``power.png``, ``verdict.json``, ``diagnose.md``.

Errors: :class:`waveforest.errors.WaveforestError` for missing or duplicate inputs.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import click
import pandas as pd

from waveforest.atomic import OutputFolder, atomic_path
from waveforest.cliutil import (
    EXISTING_FILE,
    OUT_DIR,
    MultiValueCommand,
    MultiValueOption,
    force_option,
    stage_options,
)
from waveforest.diagnose.figures import gap_figure, power_figure
from waveforest.diagnose.missing_effects import (
    final_verdict,
    run_diagnosis,
    summary_markdown,
    verdict_record,
    verdict_text,
)
from waveforest.diagnose.power import FloorCalibration
from waveforest.diagnose.search import SearchResult, SearchSettings
from waveforest.diagnose.strata import StrataSettings, with_pulses_under_crowns, with_ring_pulses
from waveforest.diagnose.twins import StudySimulator
from waveforest.errors import WaveforestError
from waveforest.io.pulses import read_pulses
from waveforest.io.results import (
    model_dict,
    read_agc_metadata,
    read_calibration_json,
    read_feature_tables,
    read_select_table,
    write_model,
)
from waveforest.io.tables import dataset_row, read_datasets, read_fields, read_targets
from waveforest.model.calibration_pulses import read_calibration_pulses
from waveforest.model.selection import dataset_of
from waveforest.model.simulate import with_sample_columns
from waveforest.sensor.calibration import CALIBRATION_EFFECTS, load_calibration
from waveforest.settings import diagnose_settings, target_pulse_settings

OUTPUT_NAMES = {
    "model": "model.yaml",
    "candidates": "candidates.csv",
    "gap": "gap_before_after.csv",
    "figure": "gap.png",
    "signatures": "signatures.csv",
    "limits": "detection_limits.csv",
    "curve": "detection_curve.csv",
    "power_figure": "power.png",
    "verdict": "verdict.json",
    "markdown": "diagnose.md",
}
"""Files written by :func:`run` (keys of :class:`DiagnoseOutputs`)."""


@dataclass
class DiagnoseOutputs:
    """What :func:`run` wrote and found."""

    paths: dict
    verdict: str
    search_verdict: str
    effects: dict
    gap_before: float
    gap_after: float
    n_pulses: int
    n_samples: int
    n_simulations: int
    seconds: float
    limits: pd.DataFrame
    text: str = ""
    """The verdict in words (``verdict.json``'s ``text``)."""


def write_outputs(out_dir, result: SearchResult, gap: pd.DataFrame, cand: pd.DataFrame, sigs: pd.DataFrame, *,
                  limits: pd.DataFrame, curve: pd.DataFrame, settings: SearchSettings, base_effects: dict, datasets,
                  keys: pd.DataFrame, seconds: float, n_fit_pulses: int | None = None,
                  floor: FloorCalibration | None = None) -> dict:
    """Write the outputs of :data:`OUTPUT_NAMES` into ``out_dir`` (atomically); returns their paths.

    ``limits`` and ``curve`` are :func:`.diagnose.power.detection_limits`' tables. The verdict
    (:func:`.diagnose.missing_effects.final_verdict`: none, named, unexplained or inconclusive)
    goes to ``verdict.json`` (:func:`.diagnose.missing_effects.verdict_record`) and to
    ``model.yaml`` as ``diagnosis_verdict``; ``model.yaml``'s ``verdict`` is the search's.
    ``settings.floor_scale`` and ``floor`` (:class:`.diagnose.power.FloorCalibration`): the
    calibrated noise floor the gaps were tested against."""
    out_dir = Path(out_dir)
    verdict, blind = final_verdict(result.verdict, limits)
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
               "diagnosis_verdict": verdict, "blind_to": list(blind),
               "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in vars(settings).items()
                            if k not in ("floors",)}},
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    write_model(paths["model"], model)
    for key, table in (("candidates", cand), ("gap", gap), ("signatures", sigs), ("limits", limits),
                       ("curve", curve)):
        with atomic_path(paths[key]) as tmp:
            table.to_csv(tmp, index=False, float_format="%.6g")

    named = ", ".join(f"{e.name} = {e.value:.3g}" for e in result.named)
    gap_figure(gap, cand, paths["figure"], title=f"verdict: {verdict}" + (f" ({named})" if named else ""))
    power_figure(curve, limits, paths["power_figure"], title="what these data could have seen")
    with atomic_path(paths["verdict"]) as tmp:
        tmp.write_text(json.dumps(verdict_record(result, gap, limits, floor), indent=2) + "\n")
    md = summary_markdown(result, gap, cand, datasets=list(datasets), n_pulses=len(keys),
                          n_samples=int(keys["sample_id"].nunique()), seconds=seconds, settings=settings,
                          base_effects=base, n_fit_pulses=n_fit_pulses, limits=limits, curve=curve)
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
    pulse_settings = target_pulse_settings(cfg)
    return {ds: read_calibration_pulses(paths[ds], targets, datasets, pulse_settings) for ds in selected
            if ds in paths}


def with_added_strata(selected: dict, agc_paths, fields, datasets_path, calibrations: dict,
                       strata: StrataSettings) -> dict:
    """Read each diagnosed dataset's AGC table and year, and add the pulses of the strata beyond
    ``select``'s table: under the crowns (``diagnose.below_crown``,
    :func:`.diagnose.strata.with_pulses_under_crowns`), then the rings
    (``diagnose.ring_m``, :func:`.diagnose.strata.with_ring_pulses`)."""

    which = " and ".join(name for name, on in (("diagnose.below_crown", strata.below_crown),
                                               ("diagnose.ring_m", strata.ring_m is not None)) if on)
    if not agc_paths or fields is None:
        raise WaveforestError(f"{which}: the AGC-normalised pulse tables (--agc) and fields.csv (--fields) are "
                              "needed to find the pulses under the crowns and in the rings around the trees "
                              "(set diagnose.ring_m: null to diagnose without the rings)")
    paths = _agc_by_dataset(agc_paths)
    missing = sorted(set(selected) - set(paths))
    if missing:
        raise WaveforestError(f"{which}: no AGC-normalised pulse table of {', '.join(missing)}")
    datasets = read_datasets(datasets_path)
    out = {}
    for ds, table in selected.items():
        agc, year = read_pulses(paths[ds]), int(dataset_row(datasets, ds, datasets_path)["year"])
        if strata.below_crown:
            table = with_pulses_under_crowns(table, agc, fields, year, calibrations[ds][0], strata)
        if strata.ring_m is not None:
            table = with_ring_pulses(table, agc, fields, year, strata)
        out[ds] = table
    return out


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


def _read_selected(selected_paths, fields, fields_path, wanted: list[str]) -> dict:
    """Dataset -> ``select`` table of the diagnosed datasets (with sample columns from fields.csv)."""

    def read_select(p):
        t = read_select_table(p)
        if fields is not None:
            t = with_sample_columns(t, fields, str(fields_path))
        return dataset_of(t, str(p)), t

    selected = {k: v for k, v in _by_dataset(selected_paths, read_select, "select table").items() if k in wanted}
    if not selected:
        raise WaveforestError(f"diagnose: no select table of the diagnosed datasets {', '.join(wanted)}")
    return selected


def _calibration_metas(calibration_paths, selected: dict) -> dict:
    """Dataset -> calibration JSON dict (noise mean and SD) of each selected dataset."""
    def read(p):
        meta = read_calibration_json(p)
        return str(meta["dataset"]), meta

    return {ds: m for ds, m in _by_dataset(calibration_paths, read, "calibration").items() if ds in selected}


def _read_calibrations(calibration_paths, system_paths, selected: dict, load: bool) -> dict:
    """Dataset -> (Calibration, calibration JSON dict) of each selected dataset; ``{}`` unless
    ``load`` (the files are still checked for a JSON per dataset)."""
    metas = _by_dataset(calibration_paths, lambda p: (str(read_calibration_json(p)["dataset"]), p), "calibration")
    systems = {}
    for ds in selected:
        if ds not in metas:
            raise WaveforestError(f"diagnose: no calibration JSON for dataset {ds}")
        systems[ds] = Path(metas[ds]).with_suffix(".parquet")
    for p in system_paths or ():
        if Path(p).stem in systems:
            systems[Path(p).stem] = Path(p)
    calibrations = {}
    if load:
        for ds in selected:
            if not systems[ds].exists():
                raise WaveforestError(f"{systems[ds]}: no such S(t) file (calibration of {ds})")
            cal = load_calibration(metas[ds], systems[ds])
            calibrations[ds] = (cal, cal.meta)
    return calibrations


def run(selected_paths, real_paths, calibration_paths, out_dir, cfg: dict, *, datasets_path,
        system_paths=None, fields_path=None, agc_paths=None, targets_path=None, simulator=None,
        progress: bool = True, force: bool = False) -> DiagnoseOutputs:
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
        Output folder (``results/diagnose``), written whole or not at all
        (:class:`waveforest.atomic.OutputFolder`; ``force``: replace it even if it holds files
        diagnose did not write).
    cfg : dict
        Loaded study config (:func:`waveforest.settings.diagnose_settings` types what is read).
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
        are tried with S(t) recalibrated under each value (:mod:`.twins`); without them,
        on top of the calibrated S(t).
    simulator : callable, optional
        ``simulate(pulses, effects, seed)`` instead of the study chain (tests).
    progress : bool
        tqdm bar over the simulations (stderr).
    """

    t_start = time.perf_counter()
    settings = diagnose_settings(cfg)
    folder = OutputFolder(out_dir, "diagnose", force=force)
    fields = read_fields(fields_path) if fields_path is not None else None
    selected = _read_selected(selected_paths, fields, fields_path, list(settings.datasets))
    added = settings.strata.below_crown or settings.strata.ring_m is not None
    calibrations = _read_calibrations(calibration_paths, system_paths, selected, simulator is None or added)
    if added:
        selected = with_added_strata(selected, agc_paths, fields, datasets_path, calibrations, settings.strata)
    if simulator is None:
        simulator = StudySimulator(selected, read_datasets(datasets_path), calibrations, settings,
                                   calibration_pulses=_calibration_pulses(agc_paths, targets_path, datasets_path,
                                                                          selected, settings.search, cfg))
    bar = _progress_bar() if progress else None
    metas = {ds: meta for ds, (_, meta) in calibrations.items()} or _calibration_metas(calibration_paths, selected)
    found = run_diagnosis(selected, read_feature_tables(real_paths), metas, simulator, settings,
                          progress=(lambda label: bar.update(1)) if bar is not None else None)
    if bar is not None:
        bar.close()
    with folder as out:
        paths = write_outputs(out, found.result, found.gap, found.candidates, found.signatures, limits=found.limits,
                              curve=found.curve, settings=replace(settings.search, floor_scale=found.floor.scale),
                              base_effects=dict(settings.base_effects),
                              datasets=sorted(selected), keys=found.keys, seconds=time.perf_counter() - t_start,
                              n_fit_pulses=None if found.fit_keys is None else len(found.fit_keys), floor=found.floor)
    paths = {k: folder.final(p) for k, p in paths.items()}
    tot = found.gap[found.gap["level"] == "total"].iloc[0]
    return DiagnoseOutputs(paths=paths, verdict=found.verdict, search_verdict=found.result.verdict,
                           effects=found.result.effects,
                           gap_before=float(tot["gap_before"]), gap_after=float(tot["gap_after"]),
                           n_pulses=int(len(found.keys)), n_samples=int(found.keys["sample_id"].nunique()),
                           n_simulations=int(found.result.n_simulations), seconds=time.perf_counter() - t_start,
                           limits=found.limits, text=verdict_text(found.result, found.limits))


def _progress_bar():
    """A tqdm bar over the simulations (stderr)."""
    from tqdm import tqdm

    return tqdm(desc="diagnose: simulations", unit="sim")


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
                   "pulses recalibrate S(t) under each value of the candidates nonlinearity and trigger_loss "
                   "(without them those candidates act on top of the calibrated S(t)); the pulses of the rings "
                   "around the trees (diagnose.ring_m) and under the crowns (diagnose.below_crown) come from them.")
@click.option("--datasets", "datasets", type=EXISTING_FILE, required=True, help="The campaign's datasets.csv.")
@click.option("--targets", "targets", type=EXISTING_FILE,
              help="The campaign's targets.csv (needed with --agc, to find the calibration-target pulses).")
@click.option("--fields", "fields", type=EXISTING_FILE,
              help="The campaign's fields.csv (needed by diagnose.ring_m and diagnose.below_crown, and by select "
                   "tables without sample positions).")
@click.option("--out", "out", type=OUT_DIR, required=True,
              help="Output folder: model.yaml, candidates.csv, gap_before_after.csv, gap.png, "
                   "signatures.csv, detection_limits.csv, detection_curve.csv, power.png, verdict.json, "
                   "diagnose.md.")
@force_option
@stage_options
def diagnose(selected, features_real, calibration, system, agc, datasets, targets, fields, out, force, cfg):
    """Find where simulation and measurement disagree, name the missing effect, show the gap shrink.

    Beyond the paper: each effect of the catalogue (src/waveforest/effects.py) is fitted on
    one half of the field samples and tested on the other (config section `diagnose`).

    Example:

    \b
    waveforest diagnose --selected select.parquet --features-real real.parquet --calibration calibration.json --system system.parquet --datasets campaign/datasets.csv --out diagnose/
    """

    res = run(list(selected), list(features_real), list(calibration), out, cfg,
              datasets_path=datasets, system_paths=list(system or ()), fields_path=fields,
              agc_paths=list(agc or ()), targets_path=targets, force=force)
    named = ", ".join(f"{k} = {v:.3g}" for k, v in res.effects.items()) or "nothing named"
    click.echo(f"diagnose: verdict {res.verdict} ({named}); gap {res.gap_before:.3g} -> {res.gap_after:.3g}; "
               f"{res.n_pulses} pulses, {res.n_samples} samples, {res.n_simulations} simulations, "
               f"{res.seconds:.0f} s -> {out}")
    click.echo(f"diagnose: {res.text}")
