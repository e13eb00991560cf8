"""Does the noise floor hold? The base model's gap over its floor on campaigns without effects.

Usage::

    python benchmarks/diagnose_floor.py RESULTS [RESULTS ...] [--sims 2]

Each RESULTS is a study's results folder on a virtual campaign without hidden effects (select,
features, calibration, agc, campaign, config/diagnose.yaml). For each, the diagnosed pulses are
simulated under the base model with ``--sims`` seeds (the diagnosis's chain and settings), and the
base model's total gap G, its noise floor F and the lower bound of G's interval are computed as
``diagnose`` reports them, with the first-echo features alone and with the whole waveform
(diagnose.features' default). Prints per campaign and seed a table line, then
``<features>_mean_gap_over_floor: value`` (mean G / F; 1 when the floor holds),
``<features>_mean_excess: value squared pooled SDs`` (mean G - F; 0 when it holds) and
``<features>_above_floor: value of N`` (runs whose interval's lower bound lies above F: false alarms),
and the mean G and F per feature of the whole waveform's set.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest import config
from waveforest.diagnose.before_after import before_after
from waveforest.diagnose.gap import DEFAULT_FEATURES, FEATURES
from waveforest.diagnose.replicate_cache import simulate_all
from waveforest.diagnose.strata import pulse_keys, real_features
from waveforest.diagnose.twins import StudySimulator
from waveforest.diagnose.waveform import with_waveform_statistics
from waveforest.io.results import read_calibration_json, read_feature_tables, read_select_table
from waveforest.io.tables import read_datasets, read_fields
from waveforest.model.simulate import with_sample_columns
from waveforest.rng import named_seeds
from waveforest.sensor.calibration import load_calibration
from waveforest.settings import diagnose_settings


def campaign_runs(results: Path, n_sims: int) -> list[dict]:
    """G, F and G's interval of the base model on one results folder, per simulation seed and feature set."""
    cfg = config.load(results / "config" / "diagnose.yaml")
    settings = diagnose_settings(cfg)
    fields = read_fields(results / "campaign" / "fields.csv")
    selected = {ds: with_sample_columns(read_select_table(results / "select" / f"{ds}.parquet"), fields, "fields.csv")
                for ds in settings.datasets}
    cals = {}
    for ds in selected:
        cal = load_calibration(results / "calibration" / f"{ds}.json", results / "calibration" / f"{ds}.parquet")
        cals[ds] = (cal, cal.meta)
    metas = {ds: read_calibration_json(results / "calibration" / f"{ds}.json") for ds in selected}
    simulate = StudySimulator(selected, read_datasets(results / "campaign" / "datasets.csv"), cals, settings)
    keys = pulse_keys(selected, settings.strata)
    feats = read_feature_tables([results / "features" / f"{ds}_real.parquet" for ds in selected])
    real = with_waveform_statistics(real_features(feats, keys, settings.strata), selected, metas)
    s = settings.search
    rows = []
    for k, seed in enumerate(named_seeds("missing_effects", int(cfg["seed"]) + 1000, n=n_sims)):
        sim = simulate_all(simulate, keys, {}, int(seed), s.replicates)
        for name, features in (("first_echo", FEATURES), ("whole_waveform", DEFAULT_FEATURES)):
            kw = {**s.gap_kw, "features": features}
            g = before_after(real, sim, sim, n_boot=s.n_boot, seed=int(seed), alpha=s.alpha, wasserstein=False, **kw)
            tot = g[g["level"] == "total"].iloc[0]
            rows.append({"results": str(results), "sim": k, "features": name, "gap": tot["gap_before"],
                         "ci_low": tot["before_ci_low"], "ci_high": tot["before_ci_high"],
                         "floor": tot["noise_floor"], "pulses": len(keys), "samples": keys["sample_id"].nunique()})
            if name == "whole_waveform":  # per feature: where an excess comes from
                for _, r in g[g["level"] == "feature"].iterrows():
                    rows.append({"results": str(results), "sim": k, "features": f"feature {r['feature']}",
                                 "gap": r["gap_before"], "ci_low": r["before_ci_low"], "ci_high": r["before_ci_high"],
                                 "floor": r["noise_floor"], "pulses": len(keys),
                                 "samples": keys["sample_id"].nunique()})
    return rows


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", nargs="+", type=Path)
    p.add_argument("--sims", type=int, default=2, help="simulation seeds per campaign")
    a = p.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    rows = []
    for r in a.results:
        rows += campaign_runs(r, a.sims)
    t = pd.DataFrame(rows)
    per_feature = t["features"].str.startswith("feature ")
    with pd.option_context("display.width", 200):
        print(t[~per_feature].round(4).to_string(index=False))
        print(t[per_feature].groupby("features")[["gap", "floor"]].mean().round(4).to_string())
    for name, g in t[~per_feature].groupby("features"):
        print(f"{name}_mean_gap_over_floor: {np.mean(g['gap'] / g['floor']):.3f}")
        print(f"{name}_mean_excess: {np.mean(g['gap'] - g['floor']):.4f} squared pooled SDs")
        print(f"{name}_above_floor: {int((g['ci_low'] > g['floor']).sum())} of {len(g)}")
    print(f"wall_time: {time.perf_counter() - t0:.1f} s")
    print(f"cpu_time: {time.process_time() - c0:.1f} s")


if __name__ == "__main__":
    main()
