"""Real vs simulated first-echo features (docs/method.md §(i1)): Table 3, Fig. 6 and Fig. 7 analogues.

Per dataset x species x feature (H, Npeaks, Apeak, FWHM, E): mean and SD of the simulated
and the real pulses, Delta % = (sim - real) / real x 100, the absolute difference, and the
numbers of pulses. Real pulses are those of ``select``'s ``comparison_set``; simulated ones
those of ``simulate``. For species listed in ``simulate.compare_min_h_m`` (birch: 1.5 m) the
waveform features (all but H) use only pulses whose first echo is higher than that
(docs/method.md §(i1): excludes ground vegetation under the birch crowns); H uses every pulse.

Beside ours: the paper's values (Table 3), and a check of what the issue asks to agree:
the order of the species by mean Apeak, E and FWHM in our simulation vs the paper's
simulation (and vs our real data), and our simulated FWHM means vs the paper's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path
from waveforest.cliutil import OUT_DIR, MultiValueCommand, input_files_option, stage_options
from waveforest.errors import WaveforestError
from waveforest.io import paper
from waveforest.report import plots
from waveforest.report.markdown import to_markdown
from waveforest.sensor.waveforms import aligned_from_table
from waveforest.stages.classify import attach_selection, read_feature_tables

FEATURES = ("H", "Npeaks", "Apeak", "FWHM", "E")
"""Features of Table 3, in the paper's order."""

ORDER_FEATURES = ("Apeak", "E", "FWHM")
"""Features whose species order is checked against the paper."""

WAVEFORM_GRID_NS = np.arange(-15.0, 45.0 + 0.25, 0.25)
"""Time grid of the Fig. 7 overlays, ns from the first echo."""

MAX_WAVEFORMS = 400
"""Most waveforms per dataset, species and source drawn in Fig. 7 (a seeded random subset)."""

_SELECT_SCALARS = ["dataset", "pulse_id", "comparison_set", "height_m", "first_echo_h_m"]


def _h_filter(df: pd.DataFrame, min_h: dict) -> np.ndarray:
    """Rows usable for the waveform features (the H rule of docs/method.md §(i1))."""
    keep = np.ones(len(df), dtype=bool)
    species = df["species"].astype(str).to_numpy()
    h = df["H"].to_numpy(float)
    for sp, lo in min_h.items():
        keep &= ~(species == sp) | (h > lo)
    return keep


def _stats(values: np.ndarray) -> tuple[float, float, int]:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return np.nan, np.nan, 0
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else np.nan, int(v.size)


def table3(real: pd.DataFrame, sim: pd.DataFrame, min_h: dict, features=FEATURES) -> pd.DataFrame:
    """The Table 3 analogue.

    Parameters
    ----------
    real, sim : DataFrame
        Feature tables (columns dataset, species and the features) of the real pulses to
        compare and of the simulated pulses.
    min_h : dict species -> m
        Height rule for the waveform features (see module docstring).

    Returns
    -------
    DataFrame with columns dataset, species, feature, sim_mean, sim_sd, real_mean, real_sd,
    delta_pct, delta, n_sim, n_real.
    """
    rows = []
    real = real.assign(_wf=_h_filter(real, min_h))
    sim = sim.assign(_wf=_h_filter(sim, min_h))
    keys = sorted(set(zip(real["dataset"], real["species"])) | set(zip(sim["dataset"], sim["species"])))
    for ds, sp in keys:
        r = real[(real["dataset"] == ds) & (real["species"] == sp)]
        s = sim[(sim["dataset"] == ds) & (sim["species"] == sp)]
        for f in features:
            rr = r if f == "H" else r[r["_wf"]]
            ss = s if f == "H" else s[s["_wf"]]
            sm, ssd, sn = _stats(ss[f].to_numpy(float) if f in ss else np.array([]))
            rm, rsd, rn = _stats(rr[f].to_numpy(float) if f in rr else np.array([]))
            delta = sm - rm
            pct = 100.0 * delta / rm if np.isfinite(rm) and rm != 0 else np.nan
            rows.append(dict(dataset=ds, species=sp, feature=f, sim_mean=sm, sim_sd=ssd,
                             real_mean=rm, real_sd=rsd, delta_pct=pct, delta=delta, n_sim=sn, n_real=rn))
    out = pd.DataFrame(rows, columns=["dataset", "species", "feature", "sim_mean", "sim_sd", "real_mean",
                                      "real_sd", "delta_pct", "delta", "n_sim", "n_real"])
    order = {f: i for i, f in enumerate(features)}
    out["_o"] = out["feature"].map(order)
    return out.sort_values(["dataset", "species", "_o"], kind="stable").drop(columns="_o").reset_index(drop=True)


def with_paper(table: pd.DataFrame, paper_table: pd.DataFrame | None = None) -> pd.DataFrame:
    """Table 3 with the paper's columns beside ours (``paper_sim_mean`` ... ``paper_delta_pct``)."""
    p = paper.table3() if paper_table is None else paper_table
    p = p.rename(columns={c: f"paper_{c}" for c in ("sim_mean", "sim_sd", "real_mean", "real_sd", "delta_pct")})
    return table.merge(p, on=["dataset", "species", "feature"], how="left")


def _order(means: pd.Series) -> str:
    m = means.dropna()
    return " > ".join(m.sort_values(ascending=False).index.astype(str)) if len(m) else ""


def order_check(table: pd.DataFrame, features=ORDER_FEATURES) -> pd.DataFrame:
    """Species order by mean feature: our sim vs the paper's sim, and our sim vs our real.

    ``table`` is :func:`with_paper` output. Returns one row per dataset x feature with the
    three orders (``a > b > c``), ``sim_matches_paper`` and ``sim_matches_real`` (None when
    the paper has no such dataset), and for FWHM the largest |our sim - paper sim| in %.
    """
    rows = []
    for (ds, f), t in table[table["feature"].isin(features)].groupby(["dataset", "feature"], sort=True):
        t = t.set_index("species")
        ours, real = _order(t["sim_mean"]), _order(t["real_mean"])
        common = t.dropna(subset=["sim_mean", "paper_sim_mean"])
        paper_order = _order(common["paper_sim_mean"]) if len(common) else ""
        ours_common = _order(common["sim_mean"]) if len(common) else ""
        row = dict(dataset=ds, feature=f, order_sim=ours, order_real=real, order_paper_sim=paper_order,
                   sim_matches_paper=(ours_common == paper_order) if paper_order else None,
                   sim_matches_real=(ours == real) if ours and real else None)
        if len(common):
            dev = 100.0 * (common["sim_mean"] - common["paper_sim_mean"]) / common["paper_sim_mean"]
            row["max_abs_dev_from_paper_sim_pct"] = float(np.abs(dev).max())
        else:
            row["max_abs_dev_from_paper_sim_pct"] = np.nan
        rows.append(row)
    return pd.DataFrame(rows, columns=["dataset", "feature", "order_sim", "order_real", "order_paper_sim",
                                       "sim_matches_paper", "sim_matches_real", "max_abs_dev_from_paper_sim_pct"])


def _read_select_scalars(paths) -> pd.DataFrame:
    frames = []
    for p in paths:
        schema = pq.read_schema(p)
        cols = [c for c in _SELECT_SCALARS if c in schema.names]
        frames.append(pq.read_table(p, columns=cols).to_pandas())
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=_SELECT_SCALARS)


def _waveforms(paths, keep: pd.DataFrame, rng: np.random.Generator) -> dict:
    """Aligned waveforms per (dataset, species) of the rows in ``keep`` (dataset, pulse_id, species)."""
    out: dict = {}
    keep = keep[["dataset", "pulse_id", "species"]].drop_duplicates(["dataset", "pulse_id"])
    cols = ["dataset", "pulse_id", "samples", "sampling_ns", "echo_time_ns"]
    for p in paths:
        ids = pq.read_table(p, columns=["dataset", "pulse_id"]).to_pandas()
        ids["_row"] = np.arange(len(ids))
        sub = ids.merge(keep, on=["dataset", "pulse_id"], how="inner").sort_values("_row")
        if sub.empty:
            continue
        t = pq.read_table(p, columns=cols).take(sub["_row"].to_numpy())
        al = aligned_from_table(t, WAVEFORM_GRID_NS)
        sub = sub.reset_index(drop=True)
        for (ds, sp), idx in sub.groupby(["dataset", "species"]).groups.items():
            out.setdefault((ds, sp), []).append(al[np.asarray(idx)])
    result = {}
    for k, parts in out.items():
        a = np.concatenate(parts)
        if len(a) > MAX_WAVEFORMS:
            a = a[np.sort(rng.choice(len(a), MAX_WAVEFORMS, replace=False))]
        result[k] = a
    return result


@dataclass(frozen=True)
class CompareOutputs:
    """Files written by :func:`run`."""

    table_csv: Path
    table_md: Path
    order_csv: Path
    figures: list


def run(real_paths, sim_paths, select_paths, sim_pulse_paths, out_dir, cfg: dict) -> CompareOutputs:
    """The ``compare`` stage.

    Parameters
    ----------
    real_paths : paths
        Feature tables of the selected real pulses (``results/features/{dataset}_real.parquet``).
    sim_paths : paths
        Feature tables of the simulated pulses (``results/features/{dataset}_sim.parquet``).
    select_paths : paths
        ``select`` tables (flags ``comparison_set``, and the real waveforms for Fig. 7).
    sim_pulse_paths : paths
        ``simulate`` chunk tables (the simulated waveforms for Fig. 7); may be empty.
    out_dir : path
        Writes ``table3.csv``, ``table3.md``, ``order_check.csv``, ``fig6_{dataset}.png`` and
        ``fig7_{dataset}.png``.
    cfg : dict
        Loaded study config (``simulate.species``, ``simulate.compare_min_h_m``, ``seed``).
    """
    out_dir = Path(out_dir)
    real = read_feature_tables(real_paths)
    sim = read_feature_tables(sim_paths)
    if select_paths:
        real = attach_selection(real, _read_select_scalars(select_paths))
    species = list(cfg["simulate"]["species"])
    if "source" in real.columns:
        real = real[real["source"].astype(str) == "real"]
    if "comparison_set" in real.columns:
        real = real[real["comparison_set"].fillna(False).astype(bool)]
    else:
        real = real[real["species"].isin(species)]
    if "source" in sim.columns:
        sim = sim[sim["source"].astype(str) == "sim"]
    sim = sim[sim["species"].isin(species)]
    datasets = [d for d in cfg["simulate"]["datasets"] if d in set(real["dataset"]) | set(sim["dataset"])]
    datasets += sorted((set(real["dataset"]) | set(sim["dataset"])) - set(datasets))
    if not datasets:
        raise WaveforestError("compare: no real or simulated pulse of the modelled species")
    min_h = {k: float(v) for k, v in cfg["simulate"]["compare_min_h_m"].items()}
    t3 = with_paper(table3(real, sim, min_h))
    checks = order_check(t3)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"csv": out_dir / "table3.csv", "md": out_dir / "table3.md", "order": out_dir / "order_check.csv"}
    with atomic_path(paths["csv"]) as tmp:
        t3.to_csv(tmp, index=False, float_format="%.6g")
    with atomic_path(paths["order"]) as tmp:
        checks.to_csv(tmp, index=False, float_format="%.6g")
    with atomic_path(paths["md"]) as tmp:
        tmp.write_text(markdown_report(t3, checks))
    figures = []
    rng = np.random.default_rng(int(cfg["seed"]))
    real_wf = _waveforms(select_paths, real, rng) if select_paths else {}
    sim_wf = _waveforms(sim_pulse_paths, sim, rng) if sim_pulse_paths else {}
    sp_order = [s for s in species]
    for ds in datasets:
        r, s = real[real["dataset"] == ds], sim[sim["dataset"] == ds]
        present = [sp for sp in sp_order if sp in set(r["species"]) | set(s["species"])]
        heights_r = {sp: r.loc[r["species"] == sp, "H"].to_numpy(float) for sp in present}
        heights_s = {sp: s.loc[s["species"] == sp, "H"].to_numpy(float) for sp in present}
        figures.append(plots.fig6_heights(heights_r, heights_s, ds, out_dir / f"fig6_{ds}.png"))
        aligned = {sp: (real_wf.get((ds, sp), np.empty((0, len(WAVEFORM_GRID_NS)))),
                        sim_wf.get((ds, sp), np.empty((0, len(WAVEFORM_GRID_NS))))) for sp in present}
        figures.append(plots.fig7_waveforms(aligned, WAVEFORM_GRID_NS, ds, out_dir / f"fig7_{ds}.png"))
    return CompareOutputs(paths["csv"], paths["md"], paths["order"], figures)


def markdown_report(t3: pd.DataFrame, checks: pd.DataFrame) -> str:
    """table3.md: our Table 3 with the paper's simulated values, and the order checks."""
    cols = ["dataset", "species", "feature", "sim_mean", "sim_sd", "real_mean", "real_sd", "delta_pct",
            "n_sim", "n_real", "paper_sim_mean", "paper_sim_sd", "paper_real_mean", "paper_delta_pct"]
    text = ["# Real vs simulated first-echo features (Table 3 analogue)", "",
            "Delta % = (sim - real) / real x 100. `paper_*`: Hovi & Korpela (2014) Table 3. "
            "Birch waveform features use echoes with H > 1.5 m only.", "",
            to_markdown(t3[cols]), "",
            "## Species order and FWHM vs the paper's simulation", "",
            to_markdown(checks)]
    return "\n".join(text)


@click.command("compare", cls=MultiValueCommand)
@input_files_option("--real", "real", "Feature tables of the selected real pulses (one or more).", required=True)
@input_files_option("--sim", "sim", "Feature tables of the simulated pulses (one or more).", required=True)
@input_files_option("--pulses-real", "pulses_real", "select tables (comparison flags and real waveforms).")
@input_files_option("--pulses-sim", "pulses_sim", "simulate chunk tables (simulated waveforms).")
@click.option("--out", type=OUT_DIR, required=True, help="Output folder (table3.csv, table3.md, fig6_*, fig7_*).")
@stage_options
def compare(real, sim, pulses_real, pulses_sim, out, cfg):
    """Real vs simulated features: the Table 3 analogue and Figures 6-7 (docs/method.md §(i1))."""

    r = run(real, sim, pulses_real, pulses_sim, out, cfg)
    click.echo(f"compare: {r.table_csv}, {r.table_md}, {r.order_csv} and {len(r.figures)} figures")
