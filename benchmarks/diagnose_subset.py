"""Is the diagnosed subset representative? Twins against the campaign on every comparison pulse
and on the diagnosis's capped subset.

Usage::

    python benchmarks/diagnose_subset.py RESULTS [RESULTS ...] [--species birch] [--sims 2] [--caps 30]

Each RESULTS is a study's results folder on a virtual campaign without hidden effects. For each,
every comparison pulse of ``--species`` (no ``diagnose.pulses_per_species`` budget, one cell per dataset) is
simulated under the base model with ``--sims`` seeds (1, 2, ...), and per feature the mean over the
datasets of d = (mean twin - mean real) / SD of the real pulses is computed on three sets of
pulses: every comparison pulse (``all``); the subset that ``diagnose.pulses_per_species`` keeps under the
study's own seed (``diagnosed``); and the subsets it keeps under ``--caps`` other seeds
(``caps``), whose spread is what the subset's d scatters by from seed to seed. Prints one row per
campaign, then, over the campaigns, ``all_d_<f>`` and its t, ``diagnosed_minus_all_<f>``,
``caps_minus_all_<f>``, ``caps_sd_<f>`` and ``diagnosed_z_<f>`` (the diagnosed subset's
difference from ``all`` over the caps' SD, mean over the campaigns: 0 with SE 1 / sqrt(n) when
the diagnosed subset is a random one).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd
from diagnose_floor import study_inputs

from waveforest import config
from waveforest.diagnose.gap import ALL_FEATURES
from waveforest.diagnose.strata import _whole_samples, dataset_share
from waveforest.settings import diagnose_settings

UNCAPPED = {"diagnose": {"pulses_per_species": None, "near_stem_m": None}}
"""The diagnosis's settings with every comparison pulse, one cell per dataset x species."""

OTHER_SEEDS = 5000
"""The ``--caps`` subsets are those of seeds OTHER_SEEDS, OTHER_SEEDS + 1, ..."""


def d_bar(real: pd.DataFrame, twins: pd.DataFrame, keys: pd.DataFrame, sd: pd.DataFrame) -> pd.Series:
    """Mean over the datasets of (mean twin - mean real) / real SD per feature, on the pulses of ``keys``."""
    k = keys[["dataset", "pulse_id"]]
    r, t = real.merge(k), twins.merge(k)
    per = [(t[t["dataset"] == ds][sd.columns].mean() - r[r["dataset"] == ds][sd.columns].mean()) / sd.loc[ds]
           for ds in sd.index]
    return pd.concat(per, axis=1).mean(axis=1)


def capped(keys: pd.DataFrame, cap: int, seed: int) -> pd.DataFrame:
    """The pulses of ``keys`` that a share of ``cap`` pulses per dataset keeps under ``seed``."""
    return pd.concat([_whole_samples(g, cap, seed) for _, g in keys.groupby("dataset")], ignore_index=True)


def campaign_row(results: Path, species: str, sims: int, caps: int) -> dict:
    settings, keys, real, simulate = study_inputs(results, overrides=UNCAPPED)
    diagnosed = diagnose_settings(config.load(results / "config" / "diagnose.yaml"))
    cap = dataset_share(diagnosed.strata.pulses_per_species, len(diagnosed.datasets))
    keys = keys[keys["species"] == species]
    real = real[real["species"] == species]
    features = [f for f in ALL_FEATURES if f in real]
    sd = real.groupby("dataset")[features].std()
    twins = pd.concat([simulate(keys, {}, s) for s in range(1, sims + 1)], ignore_index=True)
    every = d_bar(real, twins, keys, sd)
    own = d_bar(real, twins, capped(keys, cap, int(settings.seed)), sd) - every
    other = pd.concat([d_bar(real, twins, capped(keys, cap, OTHER_SEEDS + s), sd) - every for s in range(caps)], axis=1)
    row = {"results": str(results), "pulses": len(keys), "samples": keys["sample_id"].nunique()}
    for f in features:
        row |= {f"all_{f}": every[f], f"diagnosed_{f}": own[f], f"caps_{f}": other.loc[f].mean(),
                f"caps_sd_{f}": other.loc[f].std(ddof=1)}
    return row


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", nargs="+", type=Path)
    p.add_argument("--species", default="birch")
    p.add_argument("--sims", type=int, default=2, help="simulation seeds of the twins")
    p.add_argument("--caps", type=int, default=30, help="caps under other seeds")
    a = p.parse_args(argv)
    t0, c0 = time.perf_counter(), time.process_time()
    rows = []
    for r in a.results:
        rows.append(campaign_row(r, a.species, a.sims, a.caps))
        print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in rows[-1].items()}, flush=True)
    t = pd.DataFrame(rows)
    n = len(t)
    for f in [c[4:] for c in t.columns if c.startswith("all_")]:
        d = t[f"all_{f}"]
        z = t[f"diagnosed_{f}"] / t[f"caps_sd_{f}"]
        tval = d.mean() / (d.std(ddof=1) / np.sqrt(n)) if n > 1 else np.nan
        print(f"all_d_{f}: {d.mean():+.4f} real SDs (t {tval:+.1f} over {n})")
        print(f"diagnosed_minus_all_{f}: {t[f'diagnosed_{f}'].mean():+.4f} real SDs")
        print(f"caps_minus_all_{f}: {t[f'caps_{f}'].mean():+.4f} real SDs")
        print(f"caps_sd_{f}: {t[f'caps_sd_{f}'].mean():.4f} real SDs")
        print(f"diagnosed_z_{f}: {z.mean():+.2f} (SE {1 / np.sqrt(n):.2f} for a random subset)")
    print(f"wall_time: {time.perf_counter() - t0:.1f} s")
    print(f"cpu_time: {time.process_time() - c0:.1f} s")


if __name__ == "__main__":
    main()
