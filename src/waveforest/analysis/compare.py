"""Real vs simulated first-echo features (docs/method.md §(i1)): Table 3, Fig. 6 and Fig. 7 analogues.

Per dataset x species x feature (H, Npeaks, Apeak, FWHM, E): mean and SD of the simulated
and the real pulses, Delta % = (sim - real) / real x 100, the absolute difference, and the
numbers of pulses. Real pulses are those of ``select``'s ``comparison_set``; simulated ones
those of ``simulate``. For species listed in ``simulate.compare_min_h_m`` (birch: 1.5 m) the
waveform features (all but H) use only pulses whose first echo is higher than that
(docs/method.md §(i1): excludes ground vegetation under the birch crowns); H uses every pulse.

Beside ours: the paper's values (Table 3), and a check of agreement with the paper:
the order of the species by mean Apeak, E and FWHM in our simulation vs the paper's
simulation (and vs our real data), and our simulated FWHM means vs the paper's.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.errors import WaveforestError
from waveforest.io import paper
from waveforest.io.pulses import read_pulses
from waveforest.rng import named_generator
from waveforest.sensor.waveforms import aligned_from_table

FEATURES = ("H", "Npeaks", "Apeak", "FWHM", "E")
"""Features of Table 3, in the paper's order."""

ORDER_FEATURES = ("Apeak", "E", "FWHM")
"""Features whose species order is checked against the paper."""

WAVEFORM_GRID_NS = np.arange(-15.0, 45.0 + 0.25, 0.25)
"""Time grid of the Fig. 7 overlays, ns from the first echo."""

MAX_WAVEFORMS = 400
"""Most waveforms per dataset, species and source drawn in Fig. 7 (a seeded random subset)."""


@dataclass(frozen=True)
class CompareSettings:
    """The comparison (config section ``simulate``: species, datasets, compare_min_h_m; the seed).

    species : modelled species, in figure order.  datasets : comparison datasets, in order
    (others found in the tables follow, sorted).  min_h_m : species -> m, the height rule of
    the waveform features.  seed : study seed (the Fig. 7 subsets).
    """

    species: tuple
    datasets: tuple
    min_h_m: dict
    seed: int


def h_filter(df: pd.DataFrame, min_h: dict) -> np.ndarray:
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
    real = real.assign(_wf=h_filter(real, min_h))
    sim = sim.assign(_wf=h_filter(sim, min_h))
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


def aligned_waveforms(paths, keep: pd.DataFrame, rng: np.random.Generator) -> dict:
    """Aligned waveforms per (dataset, species) of the rows in ``keep`` (dataset, pulse_id, species)."""
    out: dict = {}
    keep = keep[["dataset", "pulse_id", "species"]].drop_duplicates(["dataset", "pulse_id"])
    cols = ["dataset", "pulse_id", "samples", "sampling_ns", "echo_time_ns"]
    for p in paths:
        ids = read_pulses(p, columns=["dataset", "pulse_id"]).to_pandas()
        ids["_row"] = np.arange(len(ids))
        sub = ids.merge(keep, on=["dataset", "pulse_id"], how="inner").sort_values("_row")
        if sub.empty:
            continue
        t = read_pulses(p, columns=cols).take(sub["_row"].to_numpy())
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
class Comparison:
    """The compared pulses and their tables (:func:`compare_features`).

    real, sim : the compared real and simulated feature rows.  datasets : in output order.
    table : :func:`table3` with the paper's columns (:func:`with_paper`).  checks : :func:`order_check`.
    """

    real: pd.DataFrame
    sim: pd.DataFrame
    datasets: list
    table: pd.DataFrame
    checks: pd.DataFrame


def compare_features(real: pd.DataFrame, sim: pd.DataFrame, settings: CompareSettings) -> Comparison:
    """Table 3 and the order checks of the real pulses to compare and the simulated ones.

    ``real``: feature rows of the selected real pulses (with ``select``'s ``comparison_set``
    when known; without it, the modelled species); ``sim``: feature rows of the simulated
    pulses. Raises WaveforestError when no pulse of a modelled species is left.
    """
    species = settings.species
    if "source" in real.columns:
        real = real[real["source"].astype(str) == "real"]
    if "comparison_set" in real.columns:
        real = real[real["comparison_set"].fillna(False).astype(bool)]
    else:
        real = real[real["species"].isin(species)]
    if "source" in sim.columns:
        sim = sim[sim["source"].astype(str) == "sim"]
    sim = sim[sim["species"].isin(species)]
    datasets = [d for d in settings.datasets if d in set(real["dataset"]) | set(sim["dataset"])]
    datasets += sorted((set(real["dataset"]) | set(sim["dataset"])) - set(datasets))
    if not datasets:
        raise WaveforestError("compare: no real or simulated pulse of the modelled species")
    t3 = with_paper(table3(real, sim, dict(settings.min_h_m)))
    return Comparison(real, sim, datasets, t3, order_check(t3))


def overlay_waveforms(comparison: Comparison, real_pulse_paths, sim_pulse_paths, seed: int) -> tuple[dict, dict]:
    """The Fig. 7 waveforms: :func:`aligned_waveforms` of the compared real pulses in the
    ``select`` tables and of the simulated ones in the ``simulate`` tables (either may be
    empty), from one generator of stream ``compare_waveforms``."""
    rng = named_generator("compare_waveforms", seed)
    real_wf = aligned_waveforms(real_pulse_paths, comparison.real, rng) if real_pulse_paths else {}
    sim_wf = aligned_waveforms(sim_pulse_paths, comparison.sim, rng) if sim_pulse_paths else {}
    return real_wf, sim_wf


def figure_panels(comparison: Comparison, species, real_wf: dict, sim_wf: dict
                  ) -> Iterator[tuple[str, dict, dict, dict]]:
    """Per dataset: (dataset, real heights, simulated heights, aligned waveforms), each a dict
    over the species of ``species`` present, as Figs. 6 and 7 take them."""
    real, sim = comparison.real, comparison.sim
    sp_order = [s for s in species]
    for ds in comparison.datasets:
        r, s = real[real["dataset"] == ds], sim[sim["dataset"] == ds]
        present = [sp for sp in sp_order if sp in set(r["species"]) | set(s["species"])]
        heights_r = {sp: r.loc[r["species"] == sp, "H"].to_numpy(float) for sp in present}
        heights_s = {sp: s.loc[s["species"] == sp, "H"].to_numpy(float) for sp in present}
        aligned = {sp: (real_wf.get((ds, sp), np.empty((0, len(WAVEFORM_GRID_NS)))),
                        sim_wf.get((ds, sp), np.empty((0, len(WAVEFORM_GRID_NS))))) for sp in present}
        yield ds, heights_r, heights_s, aligned
