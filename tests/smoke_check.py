"""Assertions on the outputs of the smoke workflow (run by .ci/run after snakemake).

Usage: python tests/smoke_check.py RESULTS_DIR CONFIG_YAML
Checks that every table is complete (each dataset, species and feature present), that
accuracies and kappas lie in [0, 1] (kappa in [-1, 1]), and that no table holds NaN where a
value is required. Exits non-zero with a list of every failure.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pandas as pd
import yaml

FEATURES = ["H", "Npeaks", "Apeak", "FWHM", "E"]


def check(results: Path, cfg: dict) -> list[str]:
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
            for key, value in _walk(c):
                leaf = key.rsplit(".", 1)[-1]
                if leaf in ("accuracy", "overall_accuracy") and not (0.0 <= value <= 1.0):
                    fails.append(f"{cls}: {key} = {value} outside [0, 1]")
                if leaf == "kappa" and not (-1.0 <= value <= 1.0):
                    fails.append(f"{cls}: {key} = {value} outside [-1, 1]")

    t3 = results / "compare/table3.csv"
    if need(t3):
        t = pd.read_csv(t3)
        for d in compare:
            for sp in cfg["simulate"]["species"]:
                sub = t[(t["dataset"].astype(str) == d) & (t["species"] == sp)]
                if sub.empty:
                    continue  # a species without enough pulses in a tiny campaign
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

    model = results / "diagnose/model.yaml"
    if need(model):
        m = yaml.safe_load(model.read_text())
        if m.get("verdict") not in ("none", "named", "unexplained"):
            fails.append(f"{model}: verdict {m.get('verdict')!r}")
        if not isinstance(m.get("effects"), list):
            fails.append(f"{model}: effects is not a list")

    html = results / "report/report.html"
    if need(html) and "Table 3" not in html.read_text():
        fails.append(f"{html}: no Table 3")
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


def main(argv: list[str]) -> int:
    results, cfg_path = Path(argv[1]), Path(argv[2])
    from waveforest import config

    cfg = config.load(cfg_path)
    fails = check(results, cfg)
    for f in fails:
        print(f"FAIL {f}")
    print(f"smoke check: {len(fails)} failure(s)")
    return 1 if fails else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
