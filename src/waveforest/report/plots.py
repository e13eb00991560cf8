"""Every figure of the stages, written as PNG with matplotlib (Agg), atomically.

- :func:`plot_cv_curve` -- the AGC fit, nested CV against b (Eq. 1, docs/method.md §(b));
- :func:`plot_system_waveform` -- the calibrated S(t) and the CFD tuning (§(e), §(f));
- :func:`fig6_heights`, :func:`fig7_waveforms` -- real vs simulated (Figs. 6-7 analogues, §(i1));
- :func:`fig8_sensitivity`, :func:`fig9_sensor` -- the studies (Figs. 8-9 analogues, §(i2), §(i3)).

:func:`pyplot` and :func:`save_png` are the one way of getting pyplot and writing a figure.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.plotting import pyplot, save_png

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


def _save(fig, path: str | Path) -> Path:
    """:func:`save_png` at the analysis figures' resolution (110 dpi, tight box); every figure is
    drawn with constrained layout, so no label overlaps the next panel."""
    return save_png(fig, path, dpi=110, bbox_inches="tight")


def _legend(ax) -> None:
    """A small legend under the panel (never over the data), if anything is labelled."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False)


def _label(ax, title: str, xlabel: str, ylabel: str) -> None:
    """Title, axis labels and :func:`_legend` of one panel."""
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    _legend(ax)


def plot_system_waveform(system, path, title: str = "System waveform S(t)", tuning=None) -> Path:
    """S(t) (line) with +-1 SD over the calibration pulses (band), FWHM in the legend; with a
    tuned CFD (``tuning``, a :class:`~waveforest.sensor.cfd_tuning.CFDTuning`), a second panel
    maps its score (largest |bias| over echo-width classes) over (f, delay)."""
    plt = pyplot()
    panels = 2 if tuning is not None and tuning.tuned else 1
    fig, axes = plt.subplots(1, panels, figsize=(6.4 * panels, 4.0), dpi=120, squeeze=False,
                             layout="constrained")
    ax = axes[0, 0]
    t, s = system.t_ns, system.s
    if system.s_sd is not None:
        ax.fill_between(t, s - system.s_sd, s + system.s_sd, color="tab:blue", alpha=0.25, lw=0, label="±1 SD over pulses")
    ax.plot(t, s, color="tab:blue", lw=1.5, label=f"S(t), FWHM {system.fwhm_ns:.2f} ns")
    ax.axvline(0.0, color="k", lw=0.8, ls=":", label="t = 0 (echo time)")
    ax.set_xlabel("time from the echo, ns")
    ax.set_ylabel("S(t), DN m² per unit σ")
    ax.set_title(title)
    ax.legend(frameon=False, fontsize=8)
    if panels == 2:
        cfd, grid = tuning.cfd, tuning.grid
        ax = axes[0, 1]
        piv = grid.pivot(index="delay_ns", columns="fraction", values="score_m")
        f, d = piv.columns.to_numpy(float), piv.index.to_numpy(float)
        im = ax.pcolormesh(f, d, 100 * piv.to_numpy(float), shading="nearest", cmap="viridis_r", vmax=20)
        fig.colorbar(im, ax=ax, label="largest |median dR| of a width class, cm")
        ax.plot([cfd.fraction], [cfd.delay_ns], marker="*", ms=14, color="tab:red", ls="none",
                label=f"tuned: f = {cfd.fraction:.2f}, delay = {cfd.delay_ns:.2f} ns")
        ax.set_xlabel("CFD fraction f")
        ax.set_ylabel("CFD delay, ns")
        ax.set_title("CFD tuning against the DR ranges (docs/method.md §(f))")
        ax.legend(fontsize=8, loc="lower left", framealpha=0.8)
    return save_png(fig, path)


def plot_cv_curve(fit, path) -> Path:
    """Nested CV of target echo amplitudes (``agc.statistic``) against b (Eq. 1), the fitted b marked."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 3.8), dpi=120, layout="constrained")
    b, cv = np.asarray(fit.b_grid), np.asarray(fit.cv_grid)
    ax.plot(b, 100 * cv, color="tab:blue")
    ax.axvline(fit.b, color="tab:red", lw=1, ls="--", label=f"b = {fit.b:.5f}, CV = {100 * fit.cv_after:.2f} %")
    ax.axhline(100 * fit.cv_before, color="grey", lw=0.8, ls=":", label=f"b = 0: CV = {100 * fit.cv_before:.2f} %")
    ax.set_xlabel("b (relative gain per AGC unit)")
    ax.set_ylabel(f"nested CV of echo {fit.statistic}, %")
    ax.set_title(f"AGC fit of {fit.dataset} (a = {fit.a:.2f}, {fit.n_fit_pulses} target pulses)")
    ax.legend(frameon=False, fontsize=8)
    return save_png(fig, path)


def fig6_heights(real: dict, sim: dict, dataset: str, path: str | Path) -> Path:
    """Echo-height histograms, real vs simulated, one panel per species (Fig. 6 analogue).

    Parameters
    ----------
    real, sim : dict species -> (n,) float, m
        First-echo heights above the sample's ground.
    """
    plt = pyplot()
    species = [s for s in real if s in sim] or list(real) or list(sim) or ["(none)"]
    fig, axes = plt.subplots(1, len(species), figsize=(4.2 * len(species), 3.4), squeeze=False,
                             layout="constrained")
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
        _label(ax, sp, "first-echo height H (m)", "density (1/m)")
    fig.suptitle(f"{dataset}: echo heights, real vs simulated")
    return _save(fig, path)


def fig7_waveforms(aligned: dict, grid_ns: np.ndarray, dataset: str, path: str | Path) -> Path:
    """Mean +- SD of waveforms aligned on the first echo, real vs simulated (Fig. 7 analogue).

    Parameters
    ----------
    aligned : dict species -> (real (n, g), sim (m, g)) DN
    grid_ns : (g,) ns relative to the first echo
    """
    plt = pyplot()
    species = list(aligned) or ["(none)"]
    fig, axes = plt.subplots(1, len(species), figsize=(4.2 * len(species), 3.4), squeeze=False,
                             layout="constrained")
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
        _label(ax, sp, "time from first echo (ns)", "waveform (DN)")
    fig.suptitle(f"{dataset}: waveforms aligned on the first echo (mean +- SD)")
    return _save(fig, path)


def fig8_sensitivity(table: pd.DataFrame, path: str | Path, source: str = "", height_m: float | None = None) -> Path:
    """Mean Apeak +- SE against each swept vegetation parameter (Fig. 8 analogue) of a birch of
    ``height_m`` (named in the title).

    ``table`` columns: parameter, value, mean_apeak, se_apeak; a row with parameter
    ``baseline`` (the species model as is) is drawn as a dashed line in every panel.
    """
    plt = pyplot()
    base = table[table["parameter"] == "baseline"]
    table = table[table["parameter"] != "baseline"]
    params = list(dict.fromkeys(table["parameter"])) or ["(none)"]
    ncol = min(2, len(params))
    nrow = int(np.ceil(len(params) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 3.4 * nrow), squeeze=False,
                             layout="constrained")
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
    crown = f"{height_m:g}-m birch" if height_m is not None else "birch"
    fig.suptitle(f"Sensitivity of simulated {crown} Apeak" + (f" ({source})" if source else ""))
    return _save(fig, path)


def fig9_sensor(table: pd.DataFrame, path: str | Path, species=(), features=()) -> Path:
    """LDA overall accuracy against each sensor parameter (Fig. 9 analogue).

    ``table`` columns: parameter, value, level (1-pulse / 5-pulse), scheme
    (resubstitution / cross_validated), accuracy. ``species`` and ``features`` name the
    classes and the LDA's features in the title, as the study ran them.
    """
    plt = pyplot()
    params = list(dict.fromkeys(table["parameter"])) or ["(none)"]
    fig, axes = plt.subplots(1, len(params), figsize=(4.4 * len(params), 3.5), squeeze=False,
                             layout="constrained")
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
    title = "Simulated " + (" / ".join(species) or "species") + ": LDA"
    fig.suptitle(title + (" on " + ", ".join(features) if features else ""))
    return _save(fig, path)
