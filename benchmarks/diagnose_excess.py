"""Where the no-effect gap's excess over its floor comes from: the campaign's way of recording.

Usage::

    python benchmarks/diagnose_excess.py RESULTS [--rays N] [--sims 4]

RESULTS is a study's results folder on a virtual campaign without hidden effects (as for
``diagnose_floor.py``), with the campaign's ``campaign/truth_pulses.parquet``. The diagnosed
pulses are simulated under the base model four ways:

* ``diagnosed``: as the diagnosis does (recorded sensor positions, ``diagnose.n_rays``);
* ``true_positions``: at the campaign's true sensor positions (the recorded minus the true
  position of each pulse: the campaign's per-strip positioning errors undone);
* ``campaign_rays``: with ``--rays`` rays per pulse (default the campaign's ``campaign.n_rays``),
  so the simulation carries the Monte Carlo noise of the campaign's "real" waveforms;
* ``both`` (the last two only when ``--rays`` differs from the diagnosis's ray count).

Each variant is simulated with ``--sims`` seeds (the diagnosis's own first, then those of
``diagnose_floor.py``): one simulation's G moves by up to half its floor from seed to seed, so a
variant's effect is the difference of the means, and the excess is a mean against the twins'
mean gap (the diagnosis's ``verdict.json``, ``floor_calibration.off_gap``). For each: the first echo's total gap G of
the first seed with its 95 % interval and the bootstrap floor F (``<variant>_gap: G [low,
high]``, ``<variant>_floor: F``), per feature ``<variant>_<feature>: G / F`` (first seed), and
``<variant>_mean_gap: mean [min, max] over the seeds``. Then, per dataset x species of the
``diagnosed`` variant, the correlation of the mean first-echo height H (real minus simulated) with the cell's mean recorded
minus true sensor z (``h_vs_strip_z_corr``), and the wall time.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
from diagnose_floor import study_inputs

from waveforest import config
from waveforest.diagnose.gap import FEATURES, gap_report, sample_universe
from waveforest.diagnose.replicate_cache import simulate_all
from waveforest.rng import named_seeds
from waveforest.stats.bootstrap import bootstrap_weights

AXES = "xyz"


def true_sensor_positions(results: Path) -> pd.DataFrame:
    """Per recorded pulse (dataset, gps_time): the true sensor position of the campaign's truth."""
    return pd.read_parquet(results / "campaign" / "truth_pulses.parquet",
                           columns=["dataset", "gps_time"] + [f"sensor_{a}" for a in AXES])


def at_true_positions(truth: pd.DataFrame):
    """A select-table map that moves every pulse (sensor and anchor) by minus its recording error."""

    def move(t: pa.Table) -> pa.Table:
        rec = t.select(["dataset", "gps_time"] + [f"sensor_{a}" for a in AXES]).to_pandas()
        m = rec.merge(truth, on=["dataset", "gps_time"], how="left", suffixes=("", "_true"))
        if m[[f"sensor_{a}_true" for a in AXES]].isna().any().any():
            raise SystemExit("truth_pulses.parquet lacks pulses of the select table")
        for a in AXES:
            err = (m[f"sensor_{a}"] - m[f"sensor_{a}_true"]).to_numpy()
            for col in (f"sensor_{a}", f"anchor_{a}"):
                t = t.set_column(t.schema.get_field_index(col), col, pa.array(t[col].to_numpy() - err))
        return t

    return move


def strip_z(results: Path, keys: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Per diagnosed pulse (dataset, pulse_id): recorded minus true sensor z, m."""
    sel = pd.concat([pd.read_parquet(results / "select" / f"{ds}.parquet",
                                     columns=["dataset", "pulse_id", "gps_time", "sensor_z"])
                     for ds in keys["dataset"].unique()])
    m = sel.merge(truth[["dataset", "gps_time", "sensor_z"]], on=["dataset", "gps_time"], suffixes=("", "_true"))
    return m.assign(dz=m["sensor_z"] - m["sensor_z_true"])[["dataset", "pulse_id", "dz"]]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", type=Path, help="results folder of a campaign without hidden effects")
    p.add_argument("--rays", type=int, default=None, help="rays of the campaign_rays variants "
                                                          "(default: the campaign's campaign.n_rays)")
    p.add_argument("--sims", type=int, default=4, help="simulation seeds per variant (default 4)")
    a = p.parse_args(argv)
    t0 = time.perf_counter()
    truth = true_sensor_positions(a.results)
    cfg = config.load(a.results / "config" / "diagnose.yaml")
    rays = a.rays or int(cfg["campaign"]["n_rays"])
    variants = {"diagnosed": ({}, None), "true_positions": ({}, at_true_positions(truth))}
    if rays != int(cfg["diagnose"]["n_rays"] or cfg["mcrt"]["n_rays"]):  # else the same simulations again
        variants.update({"campaign_rays": ({"diagnose": {"n_rays": rays}}, None),
                         "both": ({"diagnose": {"n_rays": rays}}, at_true_positions(truth))})
    else:
        print(f"campaign_rays: {rays} rays, as the diagnosis traces (variants campaign_rays and both skipped)")
    first = None
    for name, (overrides, geometry) in variants.items():
        settings, keys, real, simulate = study_inputs(a.results, None, overrides, geometry)
        s = settings.search
        _, s_after, s_boot = named_seeds("missing_effects", int(settings.seed), n=3)
        seeds = [int(s_after)] + [int(x) for x in named_seeds("missing_effects", int(settings.seed) + 1000,
                                                                n=a.sims - 1)]
        gaps = []
        for k, seed in enumerate(seeds):
            sim = simulate_all(simulate, keys, {}, seed, s.replicates)
            universe = sample_universe(real, sim)
            rep = gap_report(real, sim, n_boot=s.n_boot, alpha=s.alpha, wasserstein=False, universe=universe,
                             weights=bootstrap_weights(universe, s.n_boot, int(s_boot)), features=FEATURES)
            tot = rep.summary.loc["total"]
            gaps.append(float(tot["gap"]))
            if k:
                continue
            print(f"{name}_gap: {tot['gap']:.4f} [{tot['ci_low']:.4f}, {tot['ci_high']:.4f}] squared pooled SDs")
            print(f"{name}_floor: {tot['noise_floor']:.4f} squared pooled SDs")
            for f in FEATURES:
                r = rep.summary.loc[f]
                print(f"{name}_{f}: {r['gap']:.4f} / {r['noise_floor']:.4f} gap / floor")
            if first is None:
                first = (keys, real, sim)
        print(f"{name}_mean_gap: {np.mean(gaps):.4f} [{min(gaps):.4f}, {max(gaps):.4f}] over {len(gaps)} seeds",
              flush=True)
    keys, real, sim = first
    dz = strip_z(a.results, keys, truth)
    cells = (real.merge(dz, on=["dataset", "pulse_id"]).groupby(["dataset", "species"])
             .agg(h_real=("H", "mean"), dz=("dz", "mean"))
             .join(sim.groupby(["dataset", "species"]).agg(h_sim=("H", "mean"))))
    corr = np.corrcoef(cells["h_real"] - cells["h_sim"], cells["dz"])[0, 1]
    print(f"h_vs_strip_z_corr: {corr:.2f} over {len(cells)} cells")
    print(f"wall_time: {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
