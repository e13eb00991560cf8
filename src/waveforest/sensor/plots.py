"""Figures of the sensor stages: S(t) with its spread and the CFD tuning, CV(b) of the AGC fit (PNG, atomic)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from waveforest.atomic import atomic_path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_system_waveform(system, path, title: str = "System waveform S(t)", tuning=None) -> Path:
    """S(t) (line) with +-1 SD over the calibration pulses (band), FWHM in the legend; with a
    tuned CFD (``tuning``, a :class:`~waveforest.sensor.cfd_tuning.CFDTuning`), a second panel
    maps its score (largest |bias| over echo-width classes) over (f, delay)."""
    plt = _pyplot()
    panels = 2 if tuning is not None and tuning.tuned else 1
    fig, axes = plt.subplots(1, panels, figsize=(6.4 * panels, 4.0), dpi=120, squeeze=False)
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
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path


def plot_cv_curve(fit, path) -> Path:
    """Nested CV of target echo amplitudes (``agc.statistic``) against b (Eq. 1), the fitted b marked."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.0, 3.8), dpi=120)
    b, cv = np.asarray(fit.b_grid), np.asarray(fit.cv_grid)
    ax.plot(b, 100 * cv, color="tab:blue")
    ax.axvline(fit.b, color="tab:red", lw=1, ls="--", label=f"b = {fit.b:.5f}, CV = {100 * fit.cv_after:.2f} %")
    ax.axhline(100 * fit.cv_before, color="grey", lw=0.8, ls=":", label=f"b = 0: CV = {100 * fit.cv_before:.2f} %")
    ax.set_xlabel("b (relative gain per AGC unit)")
    ax.set_ylabel(f"nested CV of echo {fit.statistic}, %")
    ax.set_title(f"AGC fit of {fit.dataset} (a = {fit.a:.2f}, {fit.n_fit_pulses} target pulses)")
    ax.legend(frameon=False, fontsize=8)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
