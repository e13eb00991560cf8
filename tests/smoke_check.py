"""Assertions on the outputs of a study (run by .ci/run after the smoke workflow).

Usage: python tests/smoke_check.py RESULTS_DIR CONFIG_YAML [--paper-scale] (``--help`` for more)

Checks that every table is complete (each dataset, species and feature present), that every
classify JSON holds all functional groups with pulses and numeric accuracies, that every
compared dataset x species has >= MIN_COMPARED real and simulated pulses, that accuracies and
kappas lie in [0, 1] (kappa in [-1, 1]), and that no table holds NaN where a value is required.
``--paper-scale`` (the default study: ``python tests/smoke_check.py results config/config.yaml
--paper-scale``) adds the paper's scale: Table 3's real pulse counts within +-25 % of the
paper's (table3_counts.csv), >= 30 pulses in a group of every dataset's Table 4, and the
studies' pulses and rays at the paper's fidelity. Exits non-zero with a list of every failure.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import pandas as pd
import yaml

FEATURES = ["H", "Npeaks", "Apeak", "FWHM", "E"]
MIN_COMPARED = 10
"""Fewest real and simulated pulses of a compared dataset x species (Table 3 cell)."""
PAPER_COUNT_TOLERANCE = 0.25
"""Largest relative difference of a Table 3 real pulse count from the paper's (--paper-scale)."""
PAPER_RAYS = 16384
"""Fewest rays per pulse at the paper's fidelity: Sobol' + roulette at 16384 rays has the error
of the paper's 30,000 random rays (docs/validation.md, MCRT variance reduction)."""


def check(results: Path, cfg: dict, paper_scale: bool = False) -> list[str]:
    fails: list[str] = []

    def need(path: Path) -> bool:
        if not path.exists():
            fails.append(f"missing output {path}")
            return False
        return True

    datasets = cfg["datasets"]
    compare = [d for d in cfg.get("simulate", {}).get("datasets", datasets) if d in datasets]

    for d in datasets:
        for rel in [f"pulses/{d}.parquet", f"agc/{d}.json", f"calibration/{d}.json", f"select/{d}.parquet",
                    f"features/{d}_real.parquet", f"classify/{d}.json"]:
            need(results / rel)
        cal = results / f"calibration/{d}.json"
        if cal.exists():
            c = json.loads(cal.read_text())
            for k in ["noise_mean", "noise_sd"]:
                if not (isinstance(c.get(k), (int, float)) and math.isfinite(c[k])):
                    fails.append(f"{cal}: {k} is not a finite number")
        cls = results / f"classify/{d}.json"
        if cls.exists():
            text = cls.read_text()
            if "NaN" in text:
                fails.append(f"{cls}: contains NaN")
            c = json.loads(text)
            fails += _check_groups(cls, c, cfg, paper_scale)
            for key, value in _walk(c):
                leaf = key.rsplit(".", 1)[-1]
                if leaf in ("accuracy", "overall_accuracy") and not (0.0 <= value <= 1.0):
                    fails.append(f"{cls}: {key} = {value} outside [0, 1]")
                if leaf == "kappa" and not (-1.0 <= value <= 1.0):
                    fails.append(f"{cls}: {key} = {value} outside [-1, 1]")

    t3 = results / "compare/table3.csv"
    paper_counts = None
    if paper_scale:
        from waveforest.io.paper import table3_counts

        paper_counts = table3_counts()
    if need(t3):
        t = pd.read_csv(t3)
        for d in compare:
            for sp in cfg["simulate"]["species"]:
                sub = t[(t["dataset"].astype(str) == d) & (t["species"] == sp)]
                if sub.empty:
                    fails.append(f"{t3}: no row for {d}/{sp}")
                    continue
                for col in ["n_real", "n_sim"]:
                    if sub[col].min() < MIN_COMPARED:
                        fails.append(f"{t3}: {d}/{sp} has {int(sub[col].min())} {col[2:]} pulses "
                                     f"(expected >= {MIN_COMPARED})")
                if paper_counts is not None:
                    fails += _check_paper_count(t3, paper_counts, d, sp, int(sub["n_real"].max()))
                missing = set(FEATURES) - set(sub["feature"])
                if missing:
                    fails.append(f"{t3}: {d}/{sp} lacks features {sorted(missing)}")
                for col in ["sim_mean", "real_mean"]:
                    if sub[col].isna().any():
                        fails.append(f"{t3}: NaN in {col} for {d}/{sp}")
        if t.empty:
            fails.append(f"{t3}: empty")

    for rel in ["sensitivity/sensitivity.csv", "sensor_study/sensor_study.csv"]:
        p = results / rel
        if need(p):
            t = pd.read_csv(p)
            if t.empty:
                fails.append(f"{p}: empty")
            acc_cols = [c for c in t.columns if "accuracy" in c]
            for c in acc_cols:
                if t[c].isna().any() or not t[c].between(0, 1).all():
                    fails.append(f"{p}: {c} has NaN or values outside [0, 1]")
            num = t.select_dtypes("number")
            if num.isna().any().any():
                fails.append(f"{p}: NaN in {list(num.columns[num.isna().any()])}")

    if paper_scale:
        fails += _check_fidelity(cfg)

    model = results / "diagnose/model.yaml"
    if need(model):
        m = yaml.safe_load(model.read_text())
        if m.get("verdict") not in ("none", "named", "unexplained"):
            fails.append(f"{model}: verdict {m.get('verdict')!r}")
        if not isinstance(m.get("effects"), list):
            fails.append(f"{model}: effects is not a list")
    verdict = results / "diagnose/verdict.json"
    if need(verdict):
        v = json.loads(verdict.read_text())
        if v.get("verdict") not in ("none", "named", "unexplained", "inconclusive"):
            fails.append(f"{verdict}: verdict {v.get('verdict')!r}")
        gap = v.get("gap") or {}
        # a gap whose interval lies above its floor never reads "none" (within the noise floor)
        if gap.get("above_floor") and v.get("verdict") in ("none", "inconclusive"):
            fails.append(f"{verdict}: verdict {v.get('verdict')!r} with the gap's interval above its floor")
        if v.get("verdict") == "inconclusive" and not v.get("blind_to"):
            fails.append(f"{verdict}: inconclusive without the effects these data cannot see")
        # "cannot see" needs the power at the test value below the required power with its whole
        # interval (or unmeasured); "at the edge" an interval that reaches it
        need_power = float(cfg["diagnose"]["power"]["power"])
        for key, blind in (("blind_to", True), ("at_edge", False)):
            for e in v.get(key) or []:
                high = (e.get("power_at_test_ci") or [None, None])[1]
                if (high is not None and high >= need_power) if blind else (high is None or high < need_power):
                    fails.append(f"{verdict}: {e.get('effect')} under {key} with power interval up to {high}")
        scale = (v.get("floor_calibration") or {}).get("scale")
        if not (isinstance(scale, (int, float)) and scale > 0):
            fails.append(f"{verdict}: floor_calibration.scale {scale!r} (expected a positive factor)")
    need(results / "diagnose/power.png")
    limits = results / "diagnose/detection_limits.csv"
    if limits.exists():
        t = pd.read_csv(limits)
        bad = t[t["smallest_detectable"].notna() & ~t["status"].eq("detected")] if "status" in t else t.iloc[:0]
        if len(bad):
            fails.append(f"{limits}: a limit outside the values tried for {bad['effect'].tolist()}")
        if {"limit_ci_low", "limit_ci_high"} <= set(t.columns):  # each limit inside its interval
            lo, hi, v = (pd.to_numeric(t[c], errors="coerce") for c in ("limit_ci_low", "limit_ci_high", "smallest_detectable"))
            out = t[(lo - v > 1e-9 * v.abs()) | (v - hi > 1e-9 * v.abs())]
            if len(out):
                fails.append(f"{limits}: a limit outside its interval for {out['effect'].tolist()}")

    html = results / "report/report.html"
    if need(html) and "Table 3" not in html.read_text():
        fails.append(f"{html}: no Table 3")
    return fails


def _check_groups(path: Path, c: dict, cfg: dict, paper_scale: bool) -> list[str]:
    """Every functional group has pulses and both levels of the main LDA have numbers."""
    fails = []
    groups = list(cfg["classify"]["groups"])
    per_group = c.get("pulses_per_group") or {}
    least = int(cfg["select"]["min_pulses"]) if paper_scale else 1
    for g in groups:
        if int(per_group.get(g, 0)) < least:
            fails.append(f"{path}: group {g} has {int(per_group.get(g, 0))} pulses (expected >= {least})")
    main = c.get("main") or {}
    for level in ("one_pulse", "mean_of_sample"):
        lv = main.get(level) or {}
        for scheme in ("resubstitution", "cross_validated"):
            acc = (lv.get(scheme) or {}).get("accuracy")
            if not isinstance(acc, (int, float)) or isinstance(acc, bool) or not math.isfinite(acc):
                fails.append(f"{path}: main.{level}.{scheme}.accuracy is {acc!r} (expected a number)")
    return fails


def _check_paper_count(path: Path, paper: pd.DataFrame, dataset: str, species: str, n_real: int) -> list[str]:
    row = paper[(paper["dataset"].astype(str) == dataset) & (paper["species"] == species)]
    if row.empty:
        return []
    n = int(row["N"].iloc[0])
    if abs(n_real - n) > PAPER_COUNT_TOLERANCE * n:
        return [f"{path}: {dataset}/{species} compares {n_real} real pulses; the paper {n} "
                f"(expected within +-{PAPER_COUNT_TOLERANCE:.0%})"]
    return []


def _check_fidelity(cfg: dict) -> list[str]:
    """The studies' pulses and rays at the paper's fidelity (docs/method.md §(i2), (i3))."""
    fails = []
    m = cfg["mcrt"]
    for study, pulses in (("sensitivity", 200), ("sensor_study", 500)):
        c = cfg[study]
        rays = int(c["n_rays"] or m["n_rays"])
        enough = rays >= (PAPER_RAYS if m["sampler"] == "sobol" and m["roulette"] > 0 else 30000)
        if not enough:
            fails.append(f"config {study}: {rays} rays ({m['sampler']}) is below the paper's fidelity")
        if int(c["pulses"]) < pulses:
            fails.append(f"config {study}.pulses: {c['pulses']} (the paper's scale: >= {pulses})")
    return fails


def _walk(obj, prefix=""):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _walk(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _walk(v, f"{prefix}[{i}]")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield prefix, obj


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of this script (``--help`` shows it)."""
    parser = argparse.ArgumentParser(
        prog="python tests/smoke_check.py",
        description="Check the outputs of a study under RESULTS_DIR against its config; print every "
                    "failure and exit 1 if there is any.")
    parser.add_argument("results", type=Path, metavar="RESULTS_DIR", help="the study's results folder")
    parser.add_argument("config", type=Path, metavar="CONFIG_YAML", help="the study's config file")
    parser.add_argument("--paper-scale", action="store_true",
                        help="also check the paper's scale (Table 3 counts, group sizes, rays and pulses)")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    """Run the checks for ``argv`` (without the program name); 0 if all pass, else 1."""
    args = parse_args(argv)
    from waveforest import config

    cfg = config.load(args.config)
    fails = check(args.results, cfg, paper_scale=args.paper_scale)
    for f in fails:
        print(f"FAIL {f}")
    print(f"smoke check: {len(fails)} failure(s)")
    return 1 if fails else 0


if __name__ == "__main__":
    sys.exit(main())
