"""Verdicts of ``diagnose`` over several virtual campaigns: false alarms and the gap's excess.

Usage::

    python benchmarks/diagnose_campaigns.py RESULTS [RESULTS ...]

Each RESULTS is a study's results folder whose ``diagnose/verdict.json`` exists (e.g. made by
``snakemake --cores 2 --config seed=N -- results/diagnose/verdict.json``); its campaign's seed
is read from ``config/diagnose.yaml``. Nothing is simulated: the figures are those of the
diagnoses. Prints per campaign a table line (seed, verdict, the base model's gap G with its
95 % interval, the calibrated floor c F, G - c F, the detection limits of understory and
xy_error), then:

* ``campaigns: N``; ``verdict_<v>: k of N`` for each verdict (on campaigns without hidden
  effects every verdict but ``none`` is a false alarm, and ``inconclusive`` says the data
  could not see the effects of the sizes that matter);
* ``above_floor: k of N``: gaps whose interval lies above the floor;
* ``mean_excess: m [lo, hi] squared pooled SDs``: the mean of G - c F with its 95 % interval
  (t over campaigns; centred on 0 when the floor holds), ``excess_sd``;
* ``mean_gap_over_floor``: the mean of G / (c F);
* ``limit_<effect>_median``: the median detection limit of understory and xy_error.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from scipy import stats

LIMITS = ("understory", "xy_error")


def campaign_row(results: Path) -> dict:
    """One campaign's verdict, gap, floor and limits (KeyError/FileNotFoundError if missing)."""
    verdict = json.loads((results / "diagnose" / "verdict.json").read_text())
    seed = yaml.safe_load((results / "config" / "diagnose.yaml").read_text()).get("seed")
    limits = pd.read_csv(results / "diagnose" / "detection_limits.csv").set_index("effect")
    gap = verdict["gap"]
    row = {"results": str(results), "seed": seed, "verdict": verdict["verdict"], "gap": gap["total"],
           "gap_lo": gap["ci"][0], "gap_hi": gap["ci"][1], "floor": gap["noise_floor"],
           "excess": gap["total"] - gap["noise_floor"], "above_floor": bool(gap["above_floor"])}
    for effect in LIMITS:
        row[effect] = float(limits.loc[effect, "smallest_detectable"]) if effect in limits.index else np.nan
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", nargs="+", type=Path)
    a = ap.parse_args(argv)
    rows = []
    for r in a.results:
        try:
            rows.append(campaign_row(r))
        except (FileNotFoundError, KeyError) as err:
            print(f"{r}: no complete diagnosis ({err})", file=sys.stderr)
            return 2
    t = pd.DataFrame(rows)
    print(t[["seed", "verdict", "gap", "gap_lo", "gap_hi", "floor", "excess", *LIMITS]].to_string(
        index=False, float_format=lambda x: f"{x:.4g}"))
    n = len(t)
    print(f"campaigns: {n}")
    for v, k in t["verdict"].value_counts().items():
        print(f"verdict_{v}: {k} of {n}")
    print(f"above_floor: {int(t['above_floor'].sum())} of {n}")
    e = t["excess"].to_numpy()
    half = stats.t.ppf(0.975, n - 1) * e.std(ddof=1) / np.sqrt(n) if n > 1 else np.nan
    print(f"mean_excess: {e.mean():.4f} [{e.mean() - half:.4f}, {e.mean() + half:.4f}] squared pooled SDs")
    print(f"excess_sd: {e.std(ddof=1) if n > 1 else np.nan:.4f} squared pooled SDs")
    print(f"mean_gap_over_floor: {(t['gap'] / t['floor']).mean():.3f}")
    for effect in LIMITS:
        print(f"limit_{effect}_median: {t[effect].median():.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
