"""The study report: one self-contained HTML page and a Markdown twin.

The report leads with the results: a summary (:mod:`.summary`: Table 3 and Table 4 beside the
paper's, the Fig. 9 trend, the diagnosis verdict and its detection limits). Then the details in
the order of the paper: real vs simulated (Table 3, Figs. 6-7), sensitivity (Fig. 8), sensor
study (Fig. 9), classification (Table 4, built here from ``classify/*.json`` with the paper's
values beside ours), the diagnosis; then how the data were prepared (calibration, selection),
and every other table (CSV) and figure (PNG) found, so nothing a run wrote is left out. Then
where the time went (Snakemake benchmark files), the config used (YAML) and the software
versions. No table cell is blank: a missing value is ``—``, in the summary with its reason.

HTML embeds figures as base64 PNG (one file to send); Markdown links them relatively.
"""

from __future__ import annotations

import base64
import html
import os
import platform
import re
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.atomic import atomic_path
from waveforest.errors import WaveforestError
from waveforest.io import paper
from waveforest.io.results import read_agc_fit, read_calibration_json, read_classify_result, read_select_columns
from waveforest.report.markdown import format_value, round_floats, shift_headings, to_html, to_markdown
from waveforest.report.source import source_parts, virtual_caveat
from waveforest.report.summary import (
    ReportSettings,
    classified_counts,
    dropped_line,
    missing,
    read_csv,
    summary_parts,
)
from waveforest.stats.proportion import wilson_interval

MAX_TABLE_ROWS = 400
"""Longest table shown in full; longer ones are cut (the CSV holds all rows)."""

SHOWN_ROWS = 12
"""Rows of a long table shown open in the HTML page; the rest fold away (``<details>``)."""

SKIP_DIRS = ("campaign", "logs", "report", ".snakemake")
"""Folders of the results tree not searched for further tables and figures."""

SELECTION_COLUMNS = ("dataset", "species", "functional_group", "sample_id", "classification_set", "comparison_set",
                     "below_crown_set")
"""Columns of the select tables counted in the selection section (those a table has)."""


@dataclass
class Section:
    """A report section: title, text paragraphs, tables and figures (in order)."""

    title: str
    # ("text", str) | ("table", caption, DataFrame) | ("figure", caption, Path)
    items: list = field(default_factory=list)

    def text(self, s: str) -> None:
        self.items.append(("text", s))

    def table(self, caption: str, df: pd.DataFrame) -> None:
        self.items.append(("table", caption, df))

    def figure(self, caption: str, path: Path) -> None:
        self.items.append(("figure", caption, Path(path)))


def _csv_if_present(sec: Section, used: set, path: Path, caption: str) -> None:
    """Add the CSV at ``path`` as a table of ``sec`` (and to ``used``) if it exists."""
    if path.exists():
        used.add(path)
        sec.table(caption, read_csv(path))


def _figure_if_present(sec: Section, used: set, path: Path, caption: str) -> None:
    """Add the figure at ``path`` to ``sec`` (and to ``used``) if it exists."""
    if path.exists():
        used.add(path)
        sec.figure(caption, path)


def _figures(sec: Section, used: set, paths, caption) -> None:
    """Add each figure of ``paths`` to ``sec`` (and to ``used``), captioned ``caption(path)``."""
    for path in paths:
        used.add(path)
        sec.figure(caption(path), path)


def _study_section(results: Path, used: set, folder: str, table: str, title: str, fill,
                   settings: ReportSettings) -> Section | None:
    """Section ``title`` of the study in ``results / folder`` when that folder holds the CSV ``table``
    (added to ``used``), filled by ``fill(section, used, folder, table as a DataFrame, settings)``;
    else None."""
    d = results / folder
    if not (d / table).exists():
        return None
    used.add(d / table)
    sec = Section(title)
    fill(sec, used, d, read_csv(d / table), settings)
    return sec


def _per_species(pairs, fmt) -> str:
    """``birch 1.0 m, ...`` from (species, value) pairs, each value written by ``fmt``."""
    return ", ".join(f"{sp} {fmt(v)}" for sp, v in pairs)


def versions() -> dict:
    """Python, waveforest and every package waveforest requires, with their installed versions.

    The list comes from the installed distribution's own requirements (pyproject.toml), so it
    names exactly what ran; ``requirements-lock.txt`` pins the same names for a rerun.
    """
    out = {"python": platform.python_version(), "platform": platform.platform(), "waveforest": metadata.version("waveforest")}
    for req in metadata.requires("waveforest") or []:
        if "extra ==" in req:
            continue
        name = re.split(r"[\s\[<>=!~;]", req, maxsplit=1)[0]
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _calibration(results: Path, used: set) -> Section | None:
    sec = Section("System waveform calibration and AGC (docs/method.md §(b), e)")
    rows = []
    for path in sorted((results / "calibration").glob("*.json")):
        used.add(path)
        try:
            meta = read_calibration_json(path, required=())
        except WaveforestError:
            continue
        row = {"dataset": path.stem}
        for k, v in meta.items():
            if isinstance(v, (int, float, str)) and not isinstance(v, bool):
                row[k] = v
        cfd = meta.get("cfd") or {}
        row.update({f"cfd_{k}": cfd[k] for k in ("fraction", "delay_ns") if k in cfd})
        if isinstance(meta.get("cfd_tuning"), dict):
            row["cfd_tuned"] = bool(meta["cfd_tuning"].get("tuned"))
        agc = results / "agc" / f"{path.stem}.json"
        if agc.exists():
            used.add(agc)
            try:
                a = read_agc_fit(agc)
                for k in ("a", "b", "cv_before", "cv_after"):
                    if isinstance(a.get(k), (int, float)):
                        row[f"agc_{k}"] = a[k]
            except WaveforestError:
                pass
        rows.append(row)
    if not rows:
        return None
    sec.table("Calibration per dataset (noise from the last samples of target pulses; AGC fit of Eq. 1; "
              "CFD tuned against the DR ranges, docs/method.md §(f))",
              pd.DataFrame(rows))
    _figures(sec, used, sorted((results / "calibration").glob("*.png")),
             lambda png: f"S(t) and CFD tuning of {png.stem}")
    return sec


def _selection(results: Path, used: set, settings: ReportSettings) -> Section | None:

    frames = []
    for p in sorted((results / "select").glob("*.parquet")):
        t = read_select_columns([p], SELECTION_COLUMNS, required=())
        frames.append(t.assign(below_crown_set=t.get("below_crown_set", False)))  # older select tables lack it
    if not frames:
        return None
    df = pd.concat(frames, ignore_index=True)
    if df.empty:
        return None
    g = df.groupby(["dataset", "functional_group", "species"], sort=True)
    t = g.agg(pulses=("species", "size"), samples=("sample_id", "nunique"),
              classification=("classification_set", "sum"), comparison=("comparison_set", "sum"),
              below_crown=("below_crown_set", "sum")).reset_index()
    sec = Section("Selected pulses (docs/method.md §(i1), i4)")
    heights = _per_species(settings.compare_height_range_m, lambda v: f"{v[0]:g}-{v[1]:g} m")
    sec.text(f"Pulses whose first DR echo hit a field sample; `classification`: single DR echo of a species "
             f"with at least {settings.select_min_pulses} pulses (select.min_pulses); `comparison`: modelled "
             f"species ({', '.join(settings.compare_species)}"
             + (f"; {heights}, simulate.height_range_m" if heights else "") + "); `below_crown`: first echo "
             "under the crown of a comparison tree, lower than the tree rule's height (diagnose only).")
    sec.table("Selected pulses per dataset and species", t)
    return sec


def _compare(sec: Section, used: set, d: Path, t3: pd.DataFrame, settings: ReportSettings) -> None:
    used.add(d / "table3.md")
    min_h = settings.compare_min_h_m
    sec.text("Delta % = (sim - real) / real x 100. `paper_*` are the values of Hovi & Korpela (2014) Table 3."
             + "".join(f" {sp.capitalize()} waveform features use first echoes higher than {v:g} m only "
                       "(simulate.compare_min_h_m)." for sp, v in min_h))
    cols = [c for c in ("dataset", "species", "feature", "sim_mean", "sim_sd", "real_mean", "real_sd",
                        "delta_pct", "n_sim", "n_real", "paper_sim_mean", "paper_sim_sd", "paper_real_mean",
                        "paper_delta_pct") if c in t3.columns]
    sec.table("Table 3 analogue, with the paper's values", t3[cols])
    _csv_if_present(sec, used, d / "order_check.csv",
                    "Species order of mean Apeak, E, FWHM: our simulation vs the paper's simulation and our real "
                    "data; largest deviation of our simulated means from the paper's")
    _figures(sec, used, sorted(d.glob("fig6_*.png")), lambda png: f"Fig. 6 analogue: echo heights, {png.stem[5:]}")
    _figures(sec, used, sorted(d.glob("fig7_*.png")), lambda png: f"Fig. 7 analogue: waveforms, {png.stem[5:]}")


def _sensitivity(sec: Section, used: set, d: Path, table: pd.DataFrame, settings: ReportSettings) -> None:
    sec.text(f"{settings.sensitivity_height_m:g}-m birch, no ground, nadir, R {settings.sensitivity_range_m:g} m, "
             f"sensor XY jitter +-{settings.sensitivity_xy_jitter_m:.2f} m; mean Apeak +- SE per setting. "
             "Paper: spherical LAD gives Apeak ~55 DN; +-10 deg mean leaf angle changes Apeak 20-30 %; leaf rho "
             "0.4 -> 0.5 raises it ~55 -> 70 DN; leaf-area scale 0.5 -> 1.5 ~50 -> 80 DN.")
    _csv_if_present(sec, used, d / "sensitivity_baseline.csv",
                    "Baseline: the birch model as is (spherical LAD, rho 0.47, tau 0.50, leaf-area scale 1)")
    sec.table("Sensitivity", table)
    _figure_if_present(sec, used, d / "fig8.png", "Fig. 8 analogue")


def by_value(t: pd.DataFrame) -> pd.DataFrame:
    """Rows of each swept ``parameter`` by ``value`` ascending (numerically; others last), the
    parameters in their first order, ties in theirs; ``t`` as is without those columns."""
    if not {"parameter", "value"} <= set(t.columns):
        return t
    rank = {p: i for i, p in enumerate(pd.unique(t["parameter"]))}
    value = pd.to_numeric(t["value"], errors="coerce").to_numpy(float)
    order = np.lexsort((np.nan_to_num(value, nan=np.inf), t["parameter"].map(rank).to_numpy()))
    return t.iloc[order].reset_index(drop=True)


def _sensor_study(sec: Section, used: set, d: Path, t: pd.DataFrame, settings: ReportSettings) -> None:
    sec.text(f"Simulated {', '.join(settings.sensor_study_species)} at {settings.sensor_study_range_m:g} m; "
             "LDA on Apeak, FWHM, E. `resubstitution` = "
             "training set used for validation (the paper's scheme); `cross_validated` = folds never split a "
             "vegetation instance. Paper: accuracy rises with footprint up to 0.30-0.36 m, then saturates "
             "(100 % for 5-pulse means at the largest footprints); pulse width and sampling matter little.")
    if not t.empty and {"parameter", "value", "level", "scheme", "accuracy"} <= set(t.columns):
        wide = t.pivot_table(index=["parameter", "value"], columns=["level", "scheme"], values="accuracy",
                             sort=False)
        wide.columns = [f"{a} {b}" for a, b in wide.columns]
        sec.table("Overall accuracy (fraction correct)", by_value(wide.reset_index()))
    else:
        sec.table("Sensor study", by_value(t))
    features = d / "sensor_study_features.csv"
    if features.exists():
        used.add(features)
        sec.table("Mean first-echo features per setting and species", by_value(read_csv(features)))
    _figure_if_present(sec, used, d / "fig9.png", "Fig. 9 analogue")


_STUDIES = (
    ("compare", "table3.csv", "Real vs simulated features (Table 3, Figs. 6-7; docs/method.md §(i1))", _compare),
    ("sensitivity", "sensitivity.csv", "Sensitivity to vegetation parameters (Fig. 8; docs/method.md §(i2))",
     _sensitivity),
    ("sensor_study", "sensor_study.csv",
     "Sensor parameters and three-species classification (Fig. 9; docs/method.md §(i3))", _sensor_study),
)
"""(folder, main CSV, title, filler) of the study sections, in report order (:func:`_study_section`)."""


def _classify(results: Path, used: set, out_dir: Path, settings: ReportSettings) -> Section | None:
    paths = sorted((results / "classify").glob("*.json"))
    if not paths:
        return None
    res = []
    for p in paths:
        used.add(p)
        try:
            res.append(read_classify_result(p))
        except WaveforestError:
            continue
    if not res:
        return None
    t4 = table4(res, paper.table4())
    with atomic_path(out_dir / "table4.csv") as tmp:
        t4.to_csv(tmp, index=False, float_format="%.6g")
    with atomic_path(out_dir / "table4.md") as tmp:
        tmp.write_text("# Real-data classification of four functional groups (Table 4 analogue)\n\n" + to_markdown(t4))
    sec = Section("Real-data classification (Table 4; docs/method.md §(i4))")
    sec.text(f"LDA of {' / '.join(settings.classify_groups)} on {' and '.join(settings.classify_features)} "
             f"normalised by the {settings.classify_normaliser} mean (classify.groups, features, normaliser). Percent correct and kappa by resubstitution (as the paper) and cross-validated with folds that "
             "never split a field sample (`cv_*`); `paper_*`: Hovi & Korpela (2014) Table 4.")
    sec.table("Table 4 analogue (also results/report/table4.csv)", t4)
    dropped = dropped_line(res)
    if dropped:
        sec.text(dropped)
    extra_rows, three_rows = [], []
    for r in res:
        for e in r.get("extra") or []:
            for level in ("one_pulse", "mean_of_sample"):
                b = e.get(level) or {}
                for scheme in ("resubstitution", "cross_validated"):
                    s = b.get(scheme)
                    if s:
                        gain = ((e.get("gain_pp") or {}).get(level) or {}).get(scheme)
                        lo, hi = wilson_interval(s["accuracy"], int(e.get("n_samples") or 0))
                        extra_rows.append({"dataset": r["dataset"], "features": "+".join(e["features"]),
                                           "level": level, "scheme": scheme,
                                           "correct_pct": 100 * s["accuracy"],
                                           "ci95_pct": f"{100 * lo:.1f}-{100 * hi:.1f}", "kappa": s["kappa"],
                                           "gain_pp": gain if gain is not None else missing(
                                               "main set has no score" if "gain_pp" in e else
                                               "classify JSON without gain_pp")})
        ts = r.get("three_species")
        for key, what in (("reason", "1-pulse"), ("multi_pulse_reason", "multi-pulse")):
            if ts and ts.get(key) and not (key == "multi_pulse_reason" and ts.get("reason") == ts[key]):
                sec.text(f"Three-species LDA, {r['dataset']}, {what}: not computed ({ts[key]}).")
        if ts:
            for level in ("one_pulse", "multi_pulse"):
                b = ts.get(level) or {}
                for scheme in ("resubstitution", "cross_validated"):
                    s = b.get(scheme)
                    if s:
                        three_rows.append({"dataset": r["dataset"], "species": ", ".join(ts["species"]),
                                           "level": level if level == "one_pulse" else f"{ts['group_size']}-pulse",
                                           "scheme": scheme, "correct_pct": 100 * s["accuracy"],
                                           "kappa": s["kappa"], "n": s["n"]})
    if extra_rows:
        sec.text("gd_* are the Gaussian decomposition's multi-echo features (docs/method.md §(f2)): gd_n echoes, "
                 "gd_E total energy, gd_later_A amplitude after the first echo, gd_depth first-to-last echo "
                 "distance, gd_last_H last-echo height; on the same pulses as the first-echo sets.")
        sec.table("Other feature sets; gain_pp = accuracy minus the main set's, percentage points "
                  "(paper: adding FWHM gains < 1 pp, max H per sample +0.4 to +7.8 pp); ci95_pct: Wilson "
                  "interval with the field samples as the independent trials (pulses of a sample are not "
                  "independent, so this is the wider, honest one)",
                  pd.DataFrame(extra_rows))
    if three_rows:
        sec.table("Three-species LDA on real data, Apeak + FWHM + E (paper: 78.6-88.3 % 1-pulse, "
                  "89.6-95.8 % 5-pulse)", pd.DataFrame(three_rows))
    for r in res:
        one = (r["main"].get("one_pulse") or {}).get("resubstitution")
        if one:
            cm = pd.DataFrame(one["confusion"], columns=[f"pred {x}" for x in one["labels"]])
            cm.insert(0, "true", one["labels"])
            sec.table(f"Confusion matrix, {r['dataset']}, 1-pulse, resubstitution", cm)
    return sec


def _diagnose(results: Path, used: set) -> Section | None:
    d = results / "diagnose"
    if not d.exists():
        return None
    sec = Section("Diagnosis: the missing effect")
    for p in sorted(d.glob("*.md")):
        used.add(p)
        sec.text(shift_headings(p.read_text().strip(), 2))
    for p in sorted(d.glob("*.yaml")):
        used.add(p)
        sec.text(f"`{p.name}` (floats to 4 significant digits):\n\n```yaml\n{round_floats(p.read_text().strip())}\n```")
    for p in sorted(d.glob("*.csv")):
        used.add(p)
        sec.table(p.name, read_csv(p))
    _figures(sec, used, sorted(d.glob("*.png")), lambda p: p.name)
    return sec if sec.items else None


def _others(results: Path, used: set) -> Section | None:
    sec = Section("Further tables and figures of the run")
    for p in sorted(results.rglob("*")):
        rel = p.relative_to(results)
        if not p.is_file() or p in used or rel.parts[0] in SKIP_DIRS or rel.parts[0] == "benchmarks":
            continue
        if p.suffix == ".csv":
            sec.table(str(rel), read_csv(p))
        elif p.suffix == ".png":
            sec.figure(str(rel), p)
    return sec if sec.items else None


def _benchmarks(results: Path) -> Section | None:
    rows = []
    for p in sorted((results / "benchmarks").rglob("*.tsv")):
        try:
            t = pd.read_csv(p, sep="\t")
        except (pd.errors.EmptyDataError, pd.errors.ParserError):
            continue
        if t.empty or "s" not in t.columns:
            continue
        rel = p.relative_to(results / "benchmarks")
        rows.append({"step": str(rel.with_suffix("")), "wall_s": float(t["s"].mean()),
                     "max_rss_mb": float(t["max_rss"].mean()) if "max_rss" in t.columns else np.nan,
                     "cpu_time_s": float(t["cpu_time"].mean()) if "cpu_time" in t.columns else np.nan})
    if not rows:
        return None
    df = pd.DataFrame(rows).sort_values("wall_s", ascending=False)
    stage = df["step"].str.split("/").str[0]
    by_stage = df.assign(stage=stage).groupby("stage", sort=False).agg(
        jobs=("step", "size"), wall_s=("wall_s", "sum"), max_rss_mb=("max_rss_mb", "max")).reset_index()
    by_stage = by_stage.sort_values("wall_s", ascending=False)
    sec = Section("Where the time went (Snakemake benchmarks)")
    sec.text(f"Sum of the wall times of all jobs: {df['wall_s'].sum():.0f} s (jobs may run in parallel).")
    sec.table("Wall time per stage", by_stage)
    sec.table("Wall time per job", df)
    return sec


def _leave_out_empty(sec: Section) -> Section:
    """``sec`` without its empty tables, and one line naming what was left out."""
    empty = [it[1] for it in sec.items if it[0] == "table" and (it[2] is None or it[2].empty)]
    if empty:
        sec.items = [it for it in sec.items if not (it[0] == "table" and (it[2] is None or it[2].empty))]
        sec.text(f"Left out, no rows: {', '.join(empty)}.")
    return sec


def collect(results: str | Path, settings: ReportSettings, out_dir: Path, config_yaml: str | None = None,
            config_path: str | None = None, config_changes=()) -> list[Section]:
    """All sections of the report of a results folder: what it ran on, the summary, the details.

    ``config_yaml``: the config used, as YAML text (None: the defaults); ``config_path``: the file
    it came from (None: the defaults); ``config_changes``: (key path, default, value) of the keys
    that differ from the defaults; ``out_dir`` receives table4.csv and table4.md.
    """
    results = Path(results)
    used: set = set()
    source = Section("What this report ran on")
    source.items.extend(source_parts(results, settings, config_path, config_changes))
    summary = Section("Summary: the results beside the paper's")
    caveat = virtual_caveat(results, settings)
    if caveat:
        summary.text(caveat)
    summary.items.extend(summary_parts(results, settings))
    sections = [source, summary]
    for folder, table, title, fill in _STUDIES:
        s = _study_section(results, used, folder, table, title, fill, settings)
        if s:
            sections.append(s)
    s = _classify(results, used, out_dir, settings)
    if s:
        sections.append(s)
    for make in (_diagnose, _calibration):
        s = make(results, used)
        if s:
            sections.append(s)
    for s in (_selection(results, used, settings), _others(results, used)):
        if s:
            sections.append(s)
    if len(sections) == 2:
        raise WaveforestError(f"{results}: no result of a run found (expected the folders a run writes, "
                              f"e.g. {', '.join(f + '/' for f, *_ in _STUDIES)}, classify/, diagnose/)")
    s = _benchmarks(results)
    if s:
        sections.append(s)
    setup = Section("Configuration and software")
    setup.text("Config used:\n\n```yaml\n" + (round_floats(config_yaml) if config_yaml else "(defaults)") + "\n```")
    setup.table("Software versions", pd.DataFrame(sorted(versions().items()), columns=["package", "version"]))
    sections.append(setup)
    return [_leave_out_empty(s) for s in sections]


# -- rendering ------------------------------------------------------------------------------

_CSS = """
body{font-family:system-ui,Segoe UI,Helvetica,Arial,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
h1{border-bottom:2px solid #1f4e79}h2{color:#1f4e79;margin-top:2em;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:12px;margin:0.5em 0 1.5em 0}
th,td{border:1px solid #ccc;padding:2px 6px;text-align:right}th{background:#eef3f8}
td:first-child,th:first-child{text-align:left}caption{text-align:left;font-weight:600;padding:4px 0}
figure{margin:1em 0}figcaption{font-size:13px;color:#555}img{max-width:100%}
pre{background:#f6f8fa;padding:0.8em;overflow:auto;font-size:12px}nav li{font-size:14px}
.tbl{overflow-x:auto;max-width:100%}code{background:#f6f8fa;padding:0 2px;font-size:90%}
details{margin:-1em 0 1.5em 0}summary{cursor:pointer;color:#1f4e79;font-size:13px}
"""


def _cut(df: pd.DataFrame) -> tuple[pd.DataFrame, str]:
    if len(df) > MAX_TABLE_ROWS:
        return df.head(MAX_TABLE_ROWS), f" (first {MAX_TABLE_ROWS} of {len(df)} rows)"
    return df, ""


def _rows_html(df: pd.DataFrame) -> str:
    return "".join("<tr>" + "".join(f"<td>{html.escape(format_value(v))}</td>" for v in row) + "</tr>"
                   for row in df.itertuples(index=False))


def _html_table(caption: str, df: pd.DataFrame) -> str:
    """A table in a box that scrolls sideways; past :data:`SHOWN_ROWS` rows, the rest fold away."""
    n_rows = len(df)
    df, note = _cut(df)
    head = "<thead><tr>" + "".join(f"<th>{html.escape(str(c))}</th>" for c in df.columns) + "</tr></thead>"
    shown = df if len(df) <= SHOWN_ROWS + 3 else df.head(SHOWN_ROWS)
    if len(shown) < len(df):
        note = f" ({n_rows} rows" + (f"; the first {MAX_TABLE_ROWS} here, all in the CSV)" if note else ")")
    out = (f'<div class="tbl"><table><caption>{html.escape(caption + note)}</caption>{head}'
           f"<tbody>{_rows_html(shown)}</tbody></table></div>")
    if len(shown) < len(df):
        out += (f"<details><summary>Show the other {len(df) - SHOWN_ROWS} rows</summary><div class=\"tbl\"><table>"
                f"{head}<tbody>{_rows_html(df.iloc[SHOWN_ROWS:])}</tbody></table></div></details>")
    return out


def render_html(sections: list[Section], title: str) -> str:
    """One self-contained HTML page (figures as base64 PNG)."""
    nav = "".join(f'<li><a href="#s{i}">{html.escape(s.title)}</a></li>' for i, s in enumerate(sections))
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1><nav><ol>{nav}</ol></nav>"]
    for i, s in enumerate(sections):
        parts.append(f'<h2 id="s{i}">{html.escape(s.title)}</h2>')
        for item in s.items:
            if item[0] == "text":
                parts.append(to_html(item[1]))
            elif item[0] == "table":
                parts.append(_html_table(item[1], item[2]))
            else:
                data = base64.b64encode(item[2].read_bytes()).decode("ascii")
                parts.append(f"<figure><img alt='{html.escape(item[1])}' src='data:image/png;base64,{data}'>"
                             f"<figcaption>{html.escape(item[1])}</figcaption></figure>")
    parts.append("</body></html>\n")
    return "".join(parts)


def render_markdown(sections: list[Section], title: str, md_dir: Path) -> str:
    """The Markdown twin; figures linked relative to ``md_dir``."""
    lines = [f"# {title}", ""]
    for s in sections:
        lines += [f"## {s.title}", ""]
        for item in s.items:
            if item[0] == "text":
                lines += [item[1], ""]
            elif item[0] == "table":
                df, note = _cut(item[2])
                lines += [f"**{item[1]}**{note}", "", to_markdown(df), ""]
            else:
                rel = os.path.relpath(item[2].resolve(), md_dir.resolve())
                lines += [f"![{item[1]}]({Path(rel).as_posix()})", ""]
    return "\n".join(lines)


def table4(results: list[dict], paper: pd.DataFrame | None = None) -> pd.DataFrame:
    """The Table 4 analogue from classify results, the paper's values beside ours.

    Columns: dataset, one_pulse_correct_pct, one_pulse_kappa, mean_of_sample_correct_pct,
    mean_of_sample_kappa, pulses_per_sample (resubstitution, as the paper), the same four
    figures cross-validated (``cv_*``), n_pulses, n_samples, and ``paper_*`` columns; the counts
    are those the accuracy was computed on (:func:`waveforest.report.summary.classified_counts`).
    """
    rows = []
    for r in results:
        m = r["main"]
        n, samples, pps, _, _ = classified_counts(r)
        row = {"dataset": r["dataset"], "n_pulses": int(n), "n_samples": int(samples),
               "pulses_per_sample": round(pps, 2)}
        for level, key in (("one_pulse", "one_pulse"), ("mean_of_sample", "mean_of_sample")):
            block = m.get(level)
            for scheme, prefix in (("resubstitution", ""), ("cross_validated", "cv_")):
                s = block.get(scheme) if block else None
                row[f"{prefix}{key}_correct_pct"] = 100.0 * s["accuracy"] if s else np.nan
                row[f"{prefix}{key}_kappa"] = s["kappa"] if s else np.nan
        rows.append(row)
    table = pd.DataFrame(rows)
    if paper is not None and not table.empty:
        p = paper.rename(columns={c: f"paper_{c}" for c in paper.columns if c != "dataset"})
        table = table.merge(p, on="dataset", how="left")
    return table
