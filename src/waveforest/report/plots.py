"""Figures of the analyses (Figs. 6-9 analogues), written as PNG with matplotlib (Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.atomic import atomic_path

H_BIN_M = 0.1
"""Bin width of the echo-height histograms (Fig. 6), m."""

REAL_COLOUR, SIM_COLOUR = "#1f4e79", "#c55a11"
PARAMETER_LABELS = {
    "mean_leaf_angle_deg": "mean leaf inclination angle (deg)",
    "leaf_rho": "leaf reflectance rho",
    "leaf_tau": "leaf transmittance tau",
    "leaf_area_scale": "leaf area scale",
    "divergence_mrad": "beam divergence (mrad)",
    "pulse_width_ns": "emitted pulse width FWHM (ns)",
    "sampling_ns": "waveform sampling interval (ns)",
}


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> Path:
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    _pyplot().close(fig)
    return path


def _legend(ax) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)


def fig6_heights(real: dict, sim: dict, dataset: str, path: str | Path) -> Path:
    """Echo-height histograms, real vs simulated, one panel per species (Fig. 6 analogue).

    Parameters
    ----------
    real, sim : dict species -> (n,) float, m
        First-echo heights above the sample's ground.
    """
    plt = _pyplot()
    species = [s for s in real if s in sim] or list(real) or list(sim) or ["(none)"]
    fig, axes = plt.subplots(1, len(species), figsize=(4.2 * len(species), 3.4), squeeze=False)
    for ax, sp in zip(axes[0], species):
        r = np.asarray(real.get(sp, []), dtype=float)
        s = np.asarray(sim.get(sp, []), dtype=float)
        r, s = r[np.isfinite(r)], s[np.isfinite(s)]
        top = max([0.5] + [x.max() for x in (r, s) if x.size])
        bins = np.arange(min([0.0] + [x.min() for x in (r, s) if x.size]), top + H_BIN_M, H_BIN_M)
        for data, colour, label in ((r, REAL_COLOUR, "real"), (s, SIM_COLOUR, "simulated")):
            if data.size:
                ax.hist(data, bins=bins, density=True, histtype="step", lw=1.6, color=colour,
                        label=f"{label} (n={data.size}, mean {data.mean():.2f} m)")
        ax.set_title(sp)
        ax.set_xlabel("first-echo height H (m)")
        ax.set_ylabel("density (1/m)")
        _legend(ax)
    fig.suptitle(f"{dataset}: echo heights, real vs simulated", y=1.03)
    return _save(fig, path)


def fig7_waveforms(aligned: dict, grid_ns: np.ndarray, dataset: str, path: str | Path) -> Path:
    """Mean +- SD of waveforms aligned on the first echo, real vs simulated (Fig. 7 analogue).

    Parameters
    ----------
    aligned : dict species -> (real (n, g), sim (m, g)) DN
    grid_ns : (g,) ns relative to the first echo
    """
    plt = _pyplot()
    species = list(aligned) or ["(none)"]
    fig, axes = plt.subplots(1, len(species), figsize=(4.2 * len(species), 3.4), squeeze=False)
    for ax, sp in zip(axes[0], species):
        for data, colour, label in zip(aligned.get(sp, ()), (REAL_COLOUR, SIM_COLOUR), ("real", "simulated")):
            data = np.asarray(data, dtype=float)
            if data.size == 0 or not np.isfinite(data).any():
                continue
            with np.errstate(all="ignore"):
                mean = np.nanmean(data, axis=0)
                sd = np.nanstd(data, axis=0)
            ax.plot(grid_ns, mean, color=colour, lw=1.5, label=f"{label} (n={data.shape[0]})")
            ax.fill_between(grid_ns, mean - sd, mean + sd, color=colour, alpha=0.2, lw=0)
        ax.set_title(sp)
        ax.set_xlabel("time from first echo (ns)")
        ax.set_ylabel("waveform (DN)")
        _legend(ax)
    fig.suptitle(f"{dataset}: waveforms aligned on the first echo (mean +- SD)", y=1.03)
    return _save(fig, path)


def fig8_sensitivity(table: pd.DataFrame, path: str | Path, source: str = "") -> Path:
    """Mean Apeak +- SE against each swept vegetation parameter (Fig. 8 analogue).

    ``table`` columns: parameter, value, mean_apeak, se_apeak; a row with parameter
    ``baseline`` (the species model as is) is drawn as a dashed line in every panel.
    """
    plt = _pyplot()
    base = table[table["parameter"] == "baseline"]
    table = table[table["parameter"] != "baseline"]
    params = list(dict.fromkeys(table["parameter"])) or ["(none)"]
    ncol = min(2, len(params))
    nrow = int(np.ceil(len(params) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.4 * nrow), squeeze=False)
    for ax, p in zip(axes.flat, params):
        t = table[table["parameter"] == p].sort_values("value")
        ax.errorbar(t["value"], t["mean_apeak"], yerr=t["se_apeak"], fmt="o-", color=SIM_COLOUR,
                    capsize=3, label="mean +- SE")
        if len(base) and np.isfinite(base["mean_apeak"].iloc[0]):
            ax.axhline(base["mean_apeak"].iloc[0], color="0.4", ls="--", lw=1, label="species model")
        ax.set_xlabel(PARAMETER_LABELS.get(p, p))
        ax.set_ylabel("mean Apeak (DN)")
        _legend(ax)
    for ax in list(axes.flat)[len(params):]:
        ax.set_visible(False)
    fig.suptitle("Sensitivity of simulated 3-m birch Apeak" + (f" ({source})" if source else ""))
    fig.tight_layout()
    return _save(fig, path)


def fig9_sensor(table: pd.DataFrame, path: str | Path) -> Path:
    """LDA overall accuracy against each sensor parameter (Fig. 9 analogue).

    ``table`` columns: parameter, value, level (1-pulse / 5-pulse), scheme
    (resubstitution / cross_validated), accuracy.
    """
    plt = _pyplot()
    params = list(dict.fromkeys(table["parameter"])) or ["(none)"]
    fig, axes = plt.subplots(1, len(params), figsize=(4.4 * len(params), 3.5), squeeze=False)
    styles = {("resubstitution", 0): "o-", ("cross_validated", 0): "o--",
              ("resubstitution", 1): "s-", ("cross_validated", 1): "s--"}
    for ax, p in zip(axes[0], params):
        t = table[table["parameter"] == p]
        for li, level in enumerate(sorted(t["level"].unique())):
            for scheme in ("resubstitution", "cross_validated"):
                u = t[(t["level"] == level) & (t["scheme"] == scheme)].sort_values("value")
                if u.empty:
                    continue
                ax.plot(u["value"], 100 * u["accuracy"], styles[(scheme, li % 2)],
                        color=(REAL_COLOUR, SIM_COLOUR)[li % 2],
                        label=f"{level}, {'training = validation' if scheme == 'resubstitution' else 'CV'}")
        ax.set_xlabel(PARAMETER_LABELS.get(p, p))
        ax.set_ylabel("overall accuracy (%)")
        ax.set_ylim(0, 102)
        _legend(ax)
    fig.suptitle("Simulated birch / raspberry / fireweed: LDA on Apeak, FWHM, E")
    fig.tight_layout()
    return _save(fig, path)
