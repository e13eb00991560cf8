"""The report's first section: the results beside the paper's, before any detail.

Four parts, each read from the stage outputs under ``results/`` and from the paper's tables of
:mod:`waveforest.io.paper`:

- Table 3: our simulated-vs-real relative differences (``compare/table3.csv``) and pulse
  counts beside the paper's, one row per dataset and species;
- Table 4: our 1-pulse and mean-of-sample accuracy and kappa per dataset
  (``classify/{dataset}.json``; resubstitution as the paper, and cross-validated) beside the paper's;
- the Fig. 9 trend (``sensor_study/sensor_study.csv``): accuracy against footprint and where
  its maximum lies, against the paper's 0.30-0.36 m;
- the diagnosis (``diagnose/model.yaml``, ``gap_before_after.csv``) with its detection limits
  (``diagnose/detection_limits.csv``).

Every cell of a summary table is text. A value we do not have is ``— (reason)`` in place,
never an empty cell (:data:`waveforest.report.markdown.NO_VALUE`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.errors import WaveforestError
from waveforest.io import paper
from waveforest.io.results import read_classify_result, read_model
from waveforest.report.markdown import NO_VALUE
from waveforest.stats.proportion import limit_interval, strongest_tried

T3_FEATURES = ("H", "Npeaks", "Apeak", "FWHM", "E")
"""Table 3's features, in the paper's order."""

RADIOMETRIC = ("Apeak", "FWHM", "E")
"""Features of the paper's "radiometric differences -19 % to +11 %"."""

LEVELS = (("one_pulse", "1-pulse"), ("mean_of_sample", "mean-of-sample"))
"""Table 4 levels: key in the classify JSON, and label."""


@dataclass(frozen=True)
class ReportSettings:
    """What the report takes from the config; every setting a sentence of the report states.

    ``data``: the campaign folder (None: the virtual campaign under ``results/campaign``);
    ``campaign_effects``: (name, value) of ``campaign.effects``;
    ``sensor_study_range_m``: the sensor study's altitude, m (footprint = divergence x range);
    the ``compare_*`` pairs are (species, metres) or (species, (low, high) metres).
    """

    datasets: tuple
    sensor_study_range_m: float
    seed: int
    data: str | None
    campaign_effects: tuple
    compare_datasets: tuple
    compare_species: tuple
    compare_height_range_m: tuple
    compare_min_h_m: tuple
    select_min_pulses: int
    sensitivity_height_m: float
    sensitivity_range_m: float
    sensitivity_xy_jitter_m: float
    sensor_study_species: tuple
    classify_features: tuple
    classify_groups: tuple
    classify_normaliser: str


def missing(reason: str) -> str:
    """The text of a cell without a value: ``— (reason)``."""
    return f"{NO_VALUE} ({reason})"


def _num(v) -> float:
    try:
        v = float(v)
    except (TypeError, ValueError):
        return np.nan
    return v


def read_csv(path: Path) -> pd.DataFrame | None:
    """The CSV at ``path``; an empty frame if it is empty or unreadable, None if it does not exist."""
    if not path.exists():
        return None
    try:
        return pd.read_csv(path)
    except (pd.errors.EmptyDataError, pd.errors.ParserError):
        return pd.DataFrame()


def fill_blanks(df: pd.DataFrame, reason: str = "no value in the source table") -> pd.DataFrame:
    """``df`` with every NaN, None or empty-string cell replaced by ``— (reason)``."""
    out = df.astype(object)
    blank = out.isna() | out.map(lambda v: isinstance(v, str) and not v.strip())
    return out.mask(blank, missing(reason))


# -- Table 3 ----------------------------------------------------------------------------------

def _t3_reason(row: pd.Series) -> str:
    n_real, n_sim = _num(row.get("n_real")), _num(row.get("n_sim"))
    if n_real == 0 and n_sim == 0:
        return missing("0 real and 0 simulated pulses")
    if n_real == 0:
        return missing("0 real pulses")
    if n_sim == 0:
        return missing("0 simulated pulses")
    if _num(row.get("real_mean")) == 0:
        return missing("real mean is 0")
    return missing("not computed")


def table3_summary(ours: pd.DataFrame | None, run_datasets=(), paper_t3: pd.DataFrame | None = None,
                   paper_counts: pd.DataFrame | None = None) -> pd.DataFrame:
    """Our Delta % per feature beside the paper's, and pulse counts, one row per dataset and species.

    Parameters
    ----------
    ours : DataFrame or None
        ``compare/table3.csv`` (dataset, species, feature, delta_pct, n_real, n_sim, ...);
        None when compare did not run.
    run_datasets : iterable of str
        Datasets of this run (to tell "not in this run" from "not in the comparison").
    paper_t3, paper_counts : DataFrame
        The paper's Table 3 and its counts (default: :mod:`waveforest.io.paper`).

    Returns
    -------
    DataFrame of text: dataset, species, ``N real / sim``, ``N paper``, then ``<f> Δ%`` and
    ``<f> Δ% paper`` per feature; rows are the paper's (dataset, species), then ours not in it.
    """
    paper_t3 = paper.table3() if paper_t3 is None else paper_t3
    paper_counts = paper.table3_counts() if paper_counts is None else paper_counts
    run_datasets = set(run_datasets)
    keys = list(dict.fromkeys(zip(paper_counts["dataset"].astype(str), paper_counts["species"].astype(str))))
    if ours is not None and not ours.empty:
        ours = ours.assign(dataset=ours["dataset"].astype(str), species=ours["species"].astype(str))
        keys += sorted(set(zip(ours["dataset"], ours["species"])) - set(keys))
    ptab = paper_t3.assign(dataset=paper_t3["dataset"].astype(str)).set_index(["dataset", "species", "feature"])
    pcount = paper_counts.assign(dataset=paper_counts["dataset"].astype(str)).set_index(["dataset", "species"])["N"]
    ours_idx = ours.set_index(["dataset", "species", "feature"]) if ours is not None and not ours.empty else None
    compared = set() if ours_idx is None else set(ours_idx.index.get_level_values(0))
    rows = []
    for ds, sp in sorted(keys, key=lambda k: (k[0] not in compared, k[0], keys.index(k))):
        if ours is None:
            absent = missing("compare not run")
        elif ds not in compared:
            absent = missing("dataset not in this run" if run_datasets and ds not in run_datasets
                             else "dataset not in comparison")
        else:
            absent = missing(f"no {sp} in comparison")
        row = {"dataset": ds, "species": sp}
        mine = ours_idx.loc[(ds, sp)] if ours_idx is not None and (ds, sp) in ours_idx.index.droplevel(2) else None
        row["N real / sim"] = (absent if mine is None
                               else f"{_count_text(mine['n_real'])} / {_count_text(mine['n_sim'])}")
        row["N paper"] = str(int(pcount[(ds, sp)])) if (ds, sp) in pcount.index else missing("not in the paper")
        for f in T3_FEATURES:
            if mine is None:
                row[f"{f} Δ%"] = absent
            elif f not in mine.index:
                row[f"{f} Δ%"] = missing(f"{f} not compared")
            else:
                v = _num(mine.loc[f, "delta_pct"])
                row[f"{f} Δ%"] = format(v, "+.1f") if np.isfinite(v) else _t3_reason(mine.loc[f])
            pv = _num(ptab["delta_pct"].get((ds, sp, f)))
            row[f"{f} Δ% paper"] = format(pv, "+.0f") if np.isfinite(pv) else missing("not in the paper")
        rows.append(row)
    return pd.DataFrame(rows)


def _count_text(n: pd.Series) -> str:
    """A pulse count over features: one number, or ``low-high`` where features differ (as Table 3)."""
    n = pd.to_numeric(n, errors="coerce").dropna().astype(int)
    if n.empty:
        return NO_VALUE
    return str(n.iloc[0]) if n.min() == n.max() else f"{n.min()}-{n.max()}"


def drop_absent(table: pd.DataFrame, what: str) -> tuple[pd.DataFrame, str | None]:
    """``table`` (of :func:`table3_summary` or :func:`table4_summary`) without the rows of datasets
    not in this run (ours ``— (dataset not in this run)``, only the paper's values), and one
    sentence naming the datasets left out of ``what``."""
    gone = table.astype(str).eq(missing("dataset not in this run")).any(axis=1)
    if not gone.any():
        return table, None
    names = sorted(set(table.loc[gone, "dataset"].astype(str)))
    return (table[~gone].reset_index(drop=True),
            f"Left out of {what}: the paper's dataset{'s' if len(names) > 1 else ''} {', '.join(names)}, "
            "not in this run.")


def _range_text(v: pd.Series, fmt: str, unit: str) -> str:
    v = v[np.isfinite(v)]
    if not len(v):
        return missing("no values")
    lo, hi = format(v.min(), fmt), format(v.max(), fmt)
    return f"{lo}{unit}" if lo == hi else f"{lo} to {hi}{unit}"


def table3_sentences(ours: pd.DataFrame | None, order: pd.DataFrame | None,
                     paper_t3: pd.DataFrame | None = None) -> str:
    """Ranges of our radiometric and height differences against the paper's, over the same datasets."""
    if ours is None or ours.empty:
        return "Table 3: " + missing("compare/table3.csv not found: the comparison did not run")
    paper_t3 = paper.table3() if paper_t3 is None else paper_t3
    ours = ours.assign(dataset=ours["dataset"].astype(str))
    p = paper_t3.assign(dataset=paper_t3["dataset"].astype(str))
    p_same = p[p["dataset"].isin(set(ours["dataset"]))]
    p_same = p_same if not p_same.empty else p
    rad = ours[ours["feature"].isin(RADIOMETRIC)]
    h = ours[ours["feature"] == "H"]
    ph = p_same[p_same["feature"] == "H"]
    s = (f"Table 3: our simulated-vs-real differences of Apeak, FWHM and E range "
         f"{_range_text(rad['delta_pct'].astype(float), '+.1f', ' %')} (paper, same datasets: "
         f"{_range_text(p_same[p_same['feature'].isin(RADIOMETRIC)]['delta_pct'].astype(float), '+.0f', ' %')}); "
         f"mean echo height differences {_range_text((h['sim_mean'] - h['real_mean']).astype(float), '+.2f', ' m')} "
         f"(paper: {_range_text((ph['sim_mean'] - ph['real_mean']).astype(float), '+.2f', ' m')}).")
    if order is not None and not order.empty and "sim_matches_real" in order.columns:
        ok = order["sim_matches_real"].astype(str).str.lower().eq("true")
        s += (f" The species order of mean {', '.join(sorted(set(order['feature'].astype(str))))} in our "
              f"simulation matches our real data in {int(ok.sum())} of {len(order)} dataset-feature pairs "
              f"(paper: all but E in 2012_27_1).")
    return s


# -- Table 4 ----------------------------------------------------------------------------------

def _reason_of(*candidates) -> str | None:
    """The first non-empty reason string among ``candidates`` (the classify JSON's own words)."""
    for c in candidates:
        if isinstance(c, dict):
            c = c.get("reason")
        if isinstance(c, str) and c.strip():
            return c.strip()
    return None


def _groups_reason(r: dict, main: dict) -> str:
    """Why no LDA, from the group counts when the JSON states no reason (older classify JSONs)."""
    ppg = r.get("pulses_per_group") or {}
    empty = list(main.get("groups_missing") or [g for g, n in ppg.items() if not n])
    if empty:
        return f"0 pulses of {', '.join(empty)}; LDA needs 2 groups with pulses"
    if not r.get("n_pulses"):
        return "0 pulses classified"
    return "fewer than 2 functional groups with pulses"


def classified_counts(r: dict) -> tuple[float, float, float, int, str | None]:
    """(pulses, samples, pulses per sample) the main accuracy of a classify JSON was computed on,
    and (pulses left out of it, why). Older JSONs counted the left-out pulses in their top-level
    ``n_pulses``: ``main``'s own counts are taken where present."""
    main = r.get("main") or {}
    top = _num(r.get("n_pulses"))
    n = _num(main["n_pulses"]) if "n_pulses" in main else top
    samples = _num(main["n_samples"]) if "n_samples" in main else _num(r.get("n_samples"))
    if "n_dropped" in main:
        d = _num(main["n_dropped"])
        dropped, why = (int(d) if np.isfinite(d) else 0), main.get("dropped_reason")
    else:
        dropped = int(top - n) if np.isfinite(top) and np.isfinite(n) and top > n else 0
        why = f"no value of {' or '.join(main.get('features') or ['its features'])}" if dropped else None
    if "n_samples" in main:
        pps = n / samples if samples else np.nan
    else:
        pps = _num(r.get("pulses_per_sample"))
    return n, samples, pps, dropped, why


def dropped_line(results: list[dict]) -> str | None:
    """One line: per reason, the datasets' pulses left out of the main LDA; None when none were."""
    by_reason: dict[str, list[str]] = {}
    for r in results:
        n, _, _, dropped, why = classified_counts(r)
        if dropped:
            by_reason.setdefault(why or "reason not recorded", []).append(
                f"{r.get('dataset')} {dropped:,} of {int(n) + dropped:,}")
    if not by_reason:
        return None
    return "Left out of the classification, so not in its pulse counts: " + "; ".join(
        f"{', '.join(parts)} pulses ({why})" for why, parts in by_reason.items()) + "."


def _level_cell(r: dict, level: str, scheme: str) -> str:
    """One Table 4 cell, "percent (κ kappa)", or ``— (reason)`` from the JSON or the group counts."""
    main = r.get("main") or {}
    block = main.get(level)
    if not isinstance(block, dict):
        return missing(_reason_of(main.get(f"{level}_reason"), main) or _groups_reason(r, main))
    s = block.get(scheme)
    if isinstance(s, dict) and np.isfinite(_num(s.get("accuracy"))):
        return f"{100 * _num(s['accuracy']):.1f} (κ {_num(s.get('kappa')):.2f})"
    why = _reason_of(s, block.get(f"{scheme}_reason"), block)
    if why is None:
        why = ("too few field samples per group for CV folds" if scheme == "cross_validated"
               else "not computed")
    return missing(why)


def table4_summary(results: list[dict], run_datasets=(), paper_t4: pd.DataFrame | None = None) -> pd.DataFrame:
    """Our accuracy (kappa) per dataset and level beside the paper's Table 4.

    Parameters
    ----------
    results : list of dict
        The ``classify/{dataset}.json`` documents (old ones without ``reason`` keys too).
    run_datasets : iterable of str
        Datasets of this run (to tell "not in this run" from "not classified").
    paper_t4 : DataFrame
        The paper's Table 4 (default: :func:`waveforest.io.paper.table4`).

    Returns
    -------
    DataFrame of text: dataset, pulses (samples), then per level ``<level> resub``,
    ``<level> CV``, ``<level> paper`` as "percent correct (κ kappa)", and pulses per sample,
    ours and the paper's; one row per dataset of the paper or of ours.
    """
    paper_t4 = paper.table4() if paper_t4 is None else paper_t4
    p = paper_t4.assign(dataset=paper_t4["dataset"].astype(str)).set_index("dataset")
    ours = {str(r.get("dataset")): r for r in results}
    run_datasets = set(run_datasets)
    rows = []
    for ds in sorted(set(p.index) | set(ours), key=lambda ds: (ds not in ours, ds)):
        r = ours.get(ds)
        absent = missing("dataset not in this run" if run_datasets and ds not in run_datasets and r is None
                         else "not classified")
        row = {"dataset": ds}
        n, samples, pps, _, _ = classified_counts(r) if r is not None else (np.nan,) * 3 + (0, None)
        row["pulses (samples)"] = absent if r is None else f"{int(n)} ({int(samples)})"
        for key, label in LEVELS:
            for scheme, tag in (("resubstitution", "resub"), ("cross_validated", "CV")):
                row[f"{label} {tag}"] = absent if r is None else _level_cell(r, key, scheme)
            if ds in p.index:
                row[f"{label} paper"] = f"{p.loc[ds, f'{key}_correct_pct']:.1f} (κ {p.loc[ds, f'{key}_kappa']:.2f})"
            else:
                row[f"{label} paper"] = missing("not in the paper")
        row["pulses/sample"] = (f"{pps:.1f}" if np.isfinite(pps) and samples
                                else absent if r is None else missing("0 samples"))
        row["pulses/sample paper"] = f"{p.loc[ds, 'pulses_per_sample']:.1f}" if ds in p.index else missing("not in the paper")
        rows.append(row)
    return pd.DataFrame(rows)


def table4_sentence(results: list[dict], paper_t4: pd.DataFrame | None = None, features=("E", "Apeak"),
                    n_groups: int = 4) -> str:
    """Ranges of our 1-pulse accuracy (resubstitution and CV) against the paper's, same datasets;
    ``features`` and ``n_groups``: the classification's (``classify.features``, ``classify.groups``)."""
    head = (f"Table 4 ({n_groups} functional groups on {' and '.join(features)}; percent correct (κ kappa); "
            "`resub` = resubstitution, the paper's scheme; `CV` = folds that never split a field sample): ")
    paper_t4 = paper.table4() if paper_t4 is None else paper_t4
    acc = {"resubstitution": [], "cross_validated": []}
    for r in results:
        block = (r.get("main") or {}).get("one_pulse") or {}
        for scheme, v in acc.items():
            sc = block.get(scheme)
            if isinstance(sc, dict) and np.isfinite(_num(sc.get("accuracy"))):
                v.append(100 * _num(sc["accuracy"]))
    if not acc["resubstitution"]:
        return head + missing("no dataset classified")
    p = paper_t4[paper_t4["dataset"].astype(str).isin({str(r.get("dataset")) for r in results})]
    paper_text = (_range_text(p["one_pulse_correct_pct"].astype(float), ".1f", " %") if len(p)
                  else missing("none of our datasets is in the paper"))
    return (head + f"our 1-pulse accuracy is {_range_text(pd.Series(acc['resubstitution']), '.1f', ' %')} by "
            f"resubstitution and {_range_text(pd.Series(acc['cross_validated'], dtype=float), '.1f', ' %')} "
            f"cross-validated; the paper's for the same datasets {paper_text} "
            f"(all {len(paper_t4)}: {_range_text(paper_t4['one_pulse_correct_pct'].astype(float), '.1f', ' %')}).")


# -- Fig. 9 -----------------------------------------------------------------------------------

def _trend(x: np.ndarray, y: np.ndarray) -> str:
    if len(x) < 3 or np.ptp(y) == 0:
        return "stays flat"
    rx, ry = pd.Series(x).rank().to_numpy(), pd.Series(y).rank().to_numpy()
    rho = float(np.corrcoef(rx, ry)[0, 1])
    return "rises" if rho > 0.5 else "falls" if rho < -0.5 else "shows no clear trend"


def _plateau(fp: np.ndarray, acc: np.ndarray, n: np.ndarray | None) -> float | None:
    """Smallest footprint from which every accuracy (%) is within one binomial SE of the maximum."""
    if n is None or not np.all(np.isfinite(n)) or np.any(n <= 0):
        return None
    k = int(np.argmax(acc))
    p = acc[k] / 100
    se = 100 * max(np.sqrt(p * (1 - p) / n[k]), 1 / n[k])
    close = acc >= acc[k] - se
    first = len(close) - int(np.argmin(close[::-1])) if not close.all() else 0
    return float(fp[first])


def fig9_sentences(ss: pd.DataFrame | None, range_m: float, paper_fig9: pd.DataFrame | None = None) -> str:
    """The Fig. 9 trend in words: accuracy against footprint, where its maximum is, vs the paper.

    Parameters
    ----------
    ss : DataFrame or None
        ``sensor_study/sensor_study.csv`` (parameter, value, level, scheme, accuracy).
    range_m : float
        Altitude of the sensor study, m (footprint = divergence x range).
    """
    paper_fig9 = paper.fig9_trend() if paper_fig9 is None else paper_fig9
    pf = paper_fig9.set_index("parameter")
    lo, hi = pf.loc["footprint_m", "low"], pf.loc["footprint_m", "high"]
    if ss is None:
        return "Fig. 9: " + missing("sensor_study/sensor_study.csv not found: the sensor study did not run")
    need = {"parameter", "value", "level", "scheme", "accuracy"}
    if ss.empty or not need <= set(ss.columns):
        return "Fig. 9: " + missing(f"sensor_study.csv lacks {', '.join(sorted(need - set(ss.columns)))} or rows")
    t = ss[ss["scheme"].astype(str) == "resubstitution"]
    div = t[t["parameter"].astype(str) == "divergence_mrad"]
    parts = []
    if div.empty:
        parts.append("Fig. 9: " + missing("no divergence setting in sensor_study.csv"))
    else:
        for i, (level, g) in enumerate(sorted(div.groupby("level"), key=lambda kv: int(str(kv[0]).split("-")[0]))):
            g = g.sort_values("value")
            fp = g["value"].to_numpy(float) * range_m / 1000.0
            acc = 100 * g["accuracy"].to_numpy(float)
            k = int(np.argmax(acc))
            if i == 0:
                where = "below" if fp[k] < lo else "above" if fp[k] > hi else "within"
                s = (f"Fig. 9 (simulated three species, resubstitution as the paper): {level} accuracy "
                     f"{_trend(fp, acc)} with footprint from {acc[0]:.1f} % at {fp[0]:.2f} m to {acc[-1]:.1f} % at "
                     f"{fp[-1]:.2f} m; its maximum, {acc[k]:.1f} %, is first reached at {fp[k]:.2f} m, {where} "
                     f"the paper's {lo:.2f}-{hi:.2f} m up to which accuracy improves")
                plateau = _plateau(fp, acc, g["n"].to_numpy(float) if "n" in g.columns else None)
                if plateau is not None and plateau < fp[k]:
                    s += f" (ours stays within one binomial SE of its maximum from {plateau:.2f} m on)"
            else:
                s = (f"{level} means {acc[0]:.1f} % to {acc[-1]:.1f} %, maximum {acc[k]:.1f} % first at "
                     f"{fp[k]:.2f} m")
            parts.append(s)
        parts = ["; ".join(parts) + "."]
    other = []
    for param, label in (("pulse_width_ns", "pulse widths"), ("sampling_ns", "sampling intervals")):
        g = t[(t["parameter"].astype(str) == param) & (t["level"].astype(str) == "1-pulse")]
        if g.empty:
            other.append(f"{label}: " + missing("not in sensor_study.csv"))
            continue
        v, a = g["value"].to_numpy(float), 100 * g["accuracy"].to_numpy(float)
        other.append(f"within {a.min():.1f}-{a.max():.1f} % over {label} {v.min():g}-{v.max():g} ns")
    claims = "; ".join(f"{p.replace('_ns', '').replace('_', ' ')}: {pf.loc[p, 'claim'].split(':')[0]}"
                       for p in ("pulse_width_ns", "sampling_ns") if p in pf.index)
    parts.append(f"1-pulse accuracy varies {' and '.join(other)} (paper: {claims}).")
    return " ".join(parts)


# -- diagnosis --------------------------------------------------------------------------------

def _ci(v) -> str:
    return f"[{_num(v[0]):.3g}, {_num(v[1]):.3g}]" if isinstance(v, list) and len(v) == 2 else missing("no interval")


def diagnosis_text(d: Path) -> str:
    """The verdict, the named effects and the gap before and after, from ``diagnose/model.yaml``."""
    path = d / "model.yaml"
    if not path.exists():
        return "Diagnosis: " + missing("diagnose/model.yaml not found: the diagnosis did not run")
    try:
        m = read_model(path)
    except WaveforestError:  # not a model.yaml of the layout: no verdict to report
        return "Diagnosis: " + missing("model.yaml holds no verdict")
    verdict = _verdict_json(d / "verdict.json")
    if verdict:  # the diagnosis's verdict (none, named, unexplained, inconclusive) with what it cannot see
        s = f"Diagnosis — verdict: {verdict.get('text') or verdict.get('verdict')}"
        s += f" ({verdict['reason']})." if verdict.get("reason") else "."
    else:
        s = f"Diagnosis — verdict: {m['verdict']}"
        s += f" ({m['reason']})." if m.get("reason") else "."
    effects = m["effects"]
    if effects:
        s += " Named: " + "; ".join(
            f"{e['name']} = {_num(e.get('value')):.3g} {_ci([e.get('ci_low'), e.get('ci_high')])}, "
            f"gap reduction {_num(e.get('gap_reduction')):.3g}" for e in effects) + "."
    gap = m.get("gap") if isinstance(m.get("gap"), dict) else {}
    if gap:
        s += (f" Gap before {_num(gap.get('before')):.3g} {_ci(gap.get('before_ci'))}, after "
              f"{_num(gap.get('after')):.3g} {_ci(gap.get('after_ci'))}; noise floor "
              f"{_num(gap.get('noise_floor')):.3g}.")
    return s


def _verdict_json(path: Path) -> dict:
    """``diagnose/verdict.json`` as a dict; {} when absent or unreadable."""
    try:
        out = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return out if isinstance(out, dict) else {}


def gap_summary(d: Path) -> pd.DataFrame | None:
    """Per-feature and total gap before and after (``gap_before_after.csv``), as text; None if absent."""
    t = read_csv(d / "gap_before_after.csv")
    if t is None or t.empty or "level" not in t.columns:
        return None
    t = t[t["level"].astype(str).isin(["feature", "total"])]
    rows = []
    for _, r in t.iterrows():
        row = {"feature": str(r.get("feature", r["level"]))}
        for col, label in (("gap_before", "gap before"), ("gap_after", "gap after"), ("noise_floor", "noise floor"),
                           ("reduction", "reduction")):
            v = _num(r.get(col))
            row[label] = f"{v:.3g}" if np.isfinite(v) else missing(f"no {label} in gap_before_after.csv")
        lo, hi = _num(r.get("reduction_ci_low")), _num(r.get("reduction_ci_high"))
        row["reduction 95 % CI"] = (f"[{lo:.3g}, {hi:.3g}]" if np.isfinite(lo) and np.isfinite(hi)
                                    else missing("no interval"))
        rows.append(row)
    return pd.DataFrame(rows) if rows else None


def detection_limits(d: Path) -> pd.DataFrame | None:
    """``detection_limits.csv`` as text, an empty ``smallest_detectable`` explained; None if absent.

    Columns in: effect, unit, smallest_detectable (empty = nothing up to upper_bound is
    detectable), limit_ci_low and limit_ci_high (its interval; absent in older tables),
    upper_bound, power, replicates.
    """
    t = read_csv(d / "detection_limits.csv")
    if t is None:
        return None
    rows = []
    for _, r in t.iterrows():
        unit = "" if pd.isna(r.get("unit")) else str(r.get("unit"))
        ub = _num(r.get("upper_bound"))
        sd = _num(r.get("smallest_detectable"))
        power, reps = _num(r.get("power")), _num(r.get("replicates"))
        rows.append({
            "effect": str(r.get("effect")),
            "weakest effect detected": (f"{sd:.3g} {unit}".strip() if np.isfinite(sd) else
                                    missing(f"nothing up to {ub:.3g} {unit} is detectable".replace("  ", " ")
                                            if np.isfinite(ub) else "nothing within the bounds is detectable")),
            "95 % interval": ((limit_interval(_num(r.get("limit_ci_low")), _num(r.get("limit_ci_high")),
                                              strongest_tried(ub, _num(r.get("test_value")), _num(r.get("power_at_bound", 0.0))))
                               or missing("no interval")) if np.isfinite(sd) else missing("no limit")),
            "range (off to this bound)": f"{ub:.3g} {unit}".strip() if np.isfinite(ub) else missing("no bound given"),
            "power": f"{power:.2f}" if np.isfinite(power) else missing("no power given"),
            "replicates": f"{int(reps)}" if np.isfinite(reps) else missing("no count given"),
        })
    return pd.DataFrame(rows, columns=["effect", "weakest effect detected", "95 % interval",
                                       "range (off to this bound)", "power", "replicates"])


def detection_sentence(dl: pd.DataFrame) -> str:
    """What the diagnosis could have seen, in words, from :func:`detection_limits`'s table."""
    seen = dl[~dl["weakest effect detected"].str.startswith(NO_VALUE)]
    text = (f"Detection limits (power {', '.join(sorted(set(dl['power'])))}): "
            + (", ".join(f"{e} from {v}" for e, v in zip(seen["effect"], seen["weakest effect detected"]))
               + " would have been detected" if len(seen) else "no effect is detectable within its bounds"))
    if 0 < len(seen) < len(dl):
        text += f"; {len(dl) - len(seen)} of {len(dl)} effects are not detectable within their bounds"
    text += (". The range tried runs from the effect off to its strongest value. For leaf_albedo the effect "
             "grows as the value falls, and clumping and nonlinearity grow as 1/value (their off is an infinite "
             "value, written 0), so for these a weaker effect has a larger value: clumping at 0.5 m is weaker "
             "than at 0.05 m. A limit between off and the weakest value simulated is interpolated")
    if set(dl["replicates"]) == {"1"}:
        text += (". Each limit rests on one pseudo-real replicate: it says where the effect was detected once, "
                 "not where it is detected with the stated power (more replicates: diagnose.power.replicates)")
    return text + "."


# -- the section ------------------------------------------------------------------------------

def classify_results(results: Path) -> list[dict]:
    """The readable ``classify/*.json`` documents of a results folder, in file-name order."""
    out = []
    for p in sorted((results / "classify").glob("*.json")):
        try:
            out.append(read_classify_result(p))
        except WaveforestError:
            continue
    return out


def summary_parts(results: str | Path, settings: ReportSettings) -> list[tuple]:
    """The summary's items in order: ("text", str) and ("table", caption, DataFrame of text)."""
    results = Path(results)
    cls = classify_results(results)
    run_datasets = list(settings.datasets) + [str(r["dataset"]) for r in cls]
    t3 = read_csv(results / "compare" / "table3.csv")
    order = read_csv(results / "compare" / "order_check.csv")
    items: list[tuple] = [("text", table3_sentences(t3, order))]
    t3_brief, left_out = drop_absent(fill_blanks(table3_summary(t3, run_datasets)), "Table 3 in brief")
    items.append(("table", "Table 3 in brief: Δ % = (sim − real) / real × 100 per feature, ours and the paper's; "
                  "N = pulses (ours: real / simulated; a range where features differ, as in Table 3)", t3_brief))
    if left_out:
        items.append(("text", left_out))
    items.append(("text", table4_sentence(cls, features=settings.classify_features,
                                          n_groups=len(settings.classify_groups))))
    t4_brief, left_out = drop_absent(fill_blanks(table4_summary(cls, run_datasets)), "Table 4 in brief")
    items.append(("table", "Table 4 in brief: ours beside the paper's", t4_brief))
    dropped = dropped_line(cls)
    if dropped:
        items.append(("text", dropped))
    if left_out:
        items.append(("text", left_out))
    ss = read_csv(results / "sensor_study" / "sensor_study.csv")
    items.append(("text", fig9_sentences(ss, settings.sensor_study_range_m)))
    d = results / "diagnose"
    items.append(("text", diagnosis_text(d)))
    dl = detection_limits(d) if d.exists() else None
    if dl is None:
        items.append(("text", "Detection limits: " + missing("detection limits not computed: "
                                                             "diagnose/detection_limits.csv not found")))
    elif dl.empty:
        items.append(("text", "Detection limits: " + missing("detection_limits.csv has no rows")))
    else:
        items.append(("text", detection_sentence(dl)))
    gap = gap_summary(d)
    if gap is not None:
        items.append(("table", "Diagnosis: gap per feature and in total, before and after the named effects",
                      fill_blanks(gap)))
    if dl is not None and not dl.empty:
        items.append(("table", "Detection limits of the diagnosis", fill_blanks(dl)))
    return items
