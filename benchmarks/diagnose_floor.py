"""Does the noise floor hold? The base model's gap over its floor on campaigns without effects.

Usage::

    python benchmarks/diagnose_floor.py RESULTS[:CONFIG] [RESULTS[:CONFIG] ...] [--sims 1] [--replicates 20]

Each RESULTS is a study's results folder on a virtual campaign without hidden effects (select,
features, calibration, agc, campaign, config/diagnose.yaml). For each, the diagnosed pulses are
simulated under the base model with ``--sims`` seeds (the first the diagnosis's own), and the
base model's total gap G, its bootstrap noise floor F, the floor calibrated as ``diagnose``
calibrates it (``scale`` x F, :func:`waveforest.diagnose.power.calibrate_floor`: the same
seeds and pool, ``--replicates`` off replicates, default 20) and the lower bound of G's interval are computed, with the first-echo features
alone and with the whole waveform (diagnose.features' default). Prints per campaign and seed a
table line, then per feature set ``<features>_mean_gap_over_floor: value`` (mean G / F),
``<features>_mean_gap_over_calibrated_floor: value`` (mean G / (scale F); 1 when the floor
holds), ``<features>_mean_excess: value squared pooled SDs`` (mean G - scale F; 0 when it holds),
``<features>_above_floor: value of N`` and ``<features>_above_calibrated_floor: value of N``
(runs whose interval's lower bound lies above the floor: the gap the diagnosis would call
significant, a false alarm here), and the mean G and F per feature of the whole waveform's set.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest import config
from waveforest.diagnose.before_after import before_after
from waveforest.diagnose.gap import ALL_FEATURES, FEATURES
from waveforest.diagnose.missing_effects import real_rows
from waveforest.diagnose.power import calibrate_floor
from waveforest.diagnose.replicate_cache import effects_key, simulate_all
from waveforest.diagnose.strata import pulse_keys
from waveforest.diagnose.twins import StudySimulator
from waveforest.io.results import read_calibration_json, read_feature_tables, read_select_table
from waveforest.io.tables import read_datasets, read_fields
from waveforest.model.simulate import with_sample_columns
from waveforest.rng import named_seeds
from waveforest.sensor.calibration import load_calibration
from waveforest.settings import diagnose_settings
from waveforest.stages.diagnose import with_added_strata


def study_inputs(results: Path, cfg_path: Path | None = None, overrides: dict | None = None, geometry=None):
    """(settings, keys, real features, simulator) of the diagnosis on one results folder (config:
    ``cfg_path``, default the folder's config/diagnose.yaml, with ``overrides`` as
    :func:`waveforest.config.load` takes them); the simulator keeps every table it made, so that
    several feature sets share its simulations. ``geometry``, if given, maps each select table
    to the one the simulator traces (the real features are always the recorded pulses')."""
    cfg = config.load(cfg_path or results / "config" / "diagnose.yaml", overrides)
    settings = diagnose_settings(cfg)
    fields = read_fields(results / "campaign" / "fields.csv")
    datasets = [ds for ds in settings.datasets if (results / "select" / f"{ds}.parquet").exists()]
    recorded = {ds: with_sample_columns(read_select_table(results / "select" / f"{ds}.parquet"), fields, "fields.csv")
                for ds in datasets}
    cals = {}
    for ds in recorded:
        cal = load_calibration(results / "calibration" / f"{ds}.json", results / "calibration" / f"{ds}.parquet")
        cals[ds] = (cal, cal.meta)
    if settings.strata.below_crown or settings.strata.ring_m is not None:  # the stage's added strata
        recorded = with_added_strata(recorded, [results / "agc" / f"{ds}.parquet" for ds in datasets], fields,
                                     results / "campaign" / "datasets.csv", cals, settings.strata)
    selected = recorded if geometry is None else {ds: geometry(t) for ds, t in recorded.items()}
    metas = {ds: read_calibration_json(results / "calibration" / f"{ds}.json") for ds in selected}
    memo: dict = {}
    study = StudySimulator(selected, read_datasets(results / "campaign" / "datasets.csv"), cals, settings)

    def simulate(pulses, effects, seed):
        key = (effects_key(effects), int(seed), len(pulses))
        if key not in memo:
            memo[key] = study(pulses, effects, seed)
        return memo[key]

    keys = pulse_keys(recorded, settings.strata)
    feats = read_feature_tables([results / "features" / f"{ds}_real.parquet" for ds in selected])
    real = real_rows(feats, keys, recorded, metas, settings.strata)
    return settings, keys, real, simulate


def campaign_runs(results: Path, n_sims: int, replicates: int, cfg_path: Path | None = None) -> list[dict]:
    """G, F, the calibrated floor and G's interval of the base model on one results folder, per
    simulation seed and feature set (config: ``cfg_path``, default the folder's config/diagnose.yaml)."""
    settings, keys, real, simulate = study_inputs(results, cfg_path)
    s = settings.search
    _, s_after, s_boot = named_seeds("missing_effects", int(settings.seed), n=3)
    seeds = [(int(s_after), int(s_boot))] + [(int(x), int(x)) for x in
                                             named_seeds("missing_effects", int(settings.seed) + 1000, n=n_sims - 1)]
    rows = []
    for name, features in (("first_echo", FEATURES), ("whole_waveform", ALL_FEATURES)):
        ss = replace(s, features=features)
        power = replace(settings.power, replicates=replicates)
        scale = calibrate_floor(keys, simulate, ss, power, settings.seed).scale
        for k, (seed, boot) in enumerate(seeds):
            sim = simulate_all(simulate, keys, {}, seed, s.replicates)
            g = before_after(real, sim, sim, n_boot=s.n_boot, seed=boot, alpha=s.alpha, wasserstein=False,
                             **ss.gap_kw)
            tot = g[g["level"] == "total"].iloc[0]
            base = {"results": str(results), "sim": k, "pulses": len(keys), "samples": keys["sample_id"].nunique(),
                    "scale": scale}
            rows.append({**base, "features": name, "gap": tot["gap_before"], "ci_low": tot["before_ci_low"],
                         "ci_high": tot["before_ci_high"], "floor": tot["noise_floor"]})
            if name == "whole_waveform":  # per feature: where an excess comes from
                for _, r in g[g["level"] == "feature"].iterrows():
                    rows.append({**base, "features": f"feature {r['feature']}", "gap": r["gap_before"],
                                 "ci_low": r["before_ci_low"], "ci_high": r["before_ci_high"],
                                 "floor": r["noise_floor"]})
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", nargs="+", help="results folder, or RESULTS:CONFIG to read another config")
    p.add_argument("--sims", type=int, default=1, help="simulation seeds per campaign (the first the diagnosis's)")
    p.add_argument("--replicates", type=int, default=20,
                   help="off replicates of the calibration (diagnose.power.replicates' default)")
    a = p.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    rows = []
    for arg in a.results:
        r, _, c = arg.partition(":")
        rows += campaign_runs(Path(r), a.sims, a.replicates, Path(c) if c else None)
    t = pd.DataFrame(rows)
    per_feature = t["features"].str.startswith("feature ")
    with pd.option_context("display.width", 200):
        print(t[~per_feature].round(4).to_string(index=False))
        print(t[per_feature].groupby("features")[["gap", "floor"]].mean().round(4).to_string())
    for name, g in t[~per_feature].groupby("features"):
        cf = g["scale"] * g["floor"]
        print(f"{name}_mean_gap_over_floor: {np.mean(g['gap'] / g['floor']):.3f}")
        print(f"{name}_mean_gap_over_calibrated_floor: {np.mean(g['gap'] / cf):.3f}")
        print(f"{name}_mean_excess: {np.mean(g['gap'] - cf):.4f} squared pooled SDs")
        print(f"{name}_above_floor: {int((g['ci_low'] > g['floor']).sum())} of {len(g)}")
        print(f"{name}_above_calibrated_floor: {int((g['ci_low'] > cf).sum())} of {len(g)}")
    print(f"wall_time: {time.perf_counter() - t0:.1f} s")
    print(f"cpu_time: {time.process_time() - c0:.1f} s")


if __name__ == "__main__":
    main()
