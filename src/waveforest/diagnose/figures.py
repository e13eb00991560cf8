"""The diagnosis figure ``gap.png``: the gap before and after, and the candidates' evidence."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.atomic import atomic_path
from waveforest.diagnose import catalogue as cat
from waveforest.plotting import pyplot

BEFORE_COLOUR, AFTER_COLOUR = "#7f7f7f", "#c55a11"
NAMED_COLOUR, OTHER_COLOUR = "#1f4e79", "#bfbfbf"


def gap_figure(gap: pd.DataFrame, candidates: pd.DataFrame, path: str | Path, *, title: str = "") -> Path:
    """Write ``gap.png`` (:func:`draw_gap_figure`; ``path`` written atomically) and return its path."""
    plt = pyplot()
    fig = draw_gap_figure(gap, candidates, title=title)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def draw_gap_figure(gap: pd.DataFrame, candidates: pd.DataFrame, *, title: str = ""):
    """The figure of ``gap.png`` (a matplotlib Figure, open: the caller closes it).

    Left: the moment gap per feature and in total, base model ("before") and extended model
    ("after"), with their bootstrap intervals (never below 0) and the base model's noise floor
    (a tick per bar). Right, only when ``candidates`` has rows: every candidate's test-half gap
    reduction with its interval, per round (named ones dark), the evidence on which the effects
    were named; without candidates the figure has the left panel alone.

    Parameters
    ----------
    gap : DataFrame
        ``gap_before_after.csv`` (:func:`.before_after.before_after`): rows with level feature/total.
    candidates : DataFrame
        ``candidates.csv`` (may be empty).
    title : str
        Figure title (e.g. the verdict).
    """
    plt = pyplot()
    rows = gap[gap["level"].isin(["feature", "total"])].reset_index(drop=True)
    n_c = len(candidates)
    if n_c:
        fig, axes = plt.subplots(1, 2, figsize=(12, max(4.2, 1.4 + 0.28 * n_c)),
                                 gridspec_kw={"width_ratios": [1.3, 1.0]}, layout="constrained")
    else:
        fig, ax0 = plt.subplots(1, 1, figsize=(6.8, 4.2), layout="constrained")
        axes = [ax0]
    ax = axes[0]
    x = np.arange(len(rows))
    for off, key, colour, label in ((-0.2, "before", BEFORE_COLOUR, "base model"),
                                    (0.2, "after", AFTER_COLOUR, "with named effects")):
        g = rows[f"gap_{key}"].to_numpy(float)
        lo = np.maximum(rows[f"{key}_ci_low"].to_numpy(float), 0.0)  # a gap is >= 0
        hi = rows[f"{key}_ci_high"].to_numpy(float)
        err = np.vstack([np.clip(g - lo, 0, None), np.clip(hi - g, 0, None)])
        ax.bar(x + off, g, 0.38, color=colour, label=label, yerr=np.nan_to_num(err), capsize=3)
    fl = rows["noise_floor"].to_numpy(float)
    ax.hlines(fl, x - 0.4, x + 0.4, colors="k", linestyles="--", linewidth=1, label="noise floor (base)")
    ax.set_xticks(x, rows["feature"].tolist(), rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("moment gap, mean of $\\bar{d}^2 + \\bar{l}^2$ (datasets pooled)")
    ax.set_title("gap between real and simulated features")
    # below the axes: a legend never covers a bar
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.28), ncol=3, frameon=False)
    if n_c:
        ax = axes[1]
        c = candidates.sort_values(["round", "rank"], ascending=[True, False]).reset_index(drop=True)
        y = np.arange(n_c)
        r = c["gap_reduction"].to_numpy(float)
        err = np.vstack([np.clip(r - c["reduction_ci_low"].to_numpy(float), 0, None),
                         np.clip(c["reduction_ci_high"].to_numpy(float) - r, 0, None)])
        named = c["named"].to_numpy(bool) if "named" in c else c["significant"].to_numpy(bool)
        ax.barh(y, r, color=np.where(named, NAMED_COLOUR, OTHER_COLOUR), xerr=np.nan_to_num(err), capsize=2)
        ax.axvline(0.0, color="k", linewidth=0.8)
        ax.set_yticks(y, [f"R{rr} {n}" for rr, n in zip(c["round"], c["name"])], fontsize=8)
        ax.set_xlabel("test-half gap reduction (95 % interval)")
        ax.set_title("candidates (dark: named)")
    if title:
        fig.suptitle(title)
    return fig


def power_figure(curve: pd.DataFrame, limits: pd.DataFrame, path: str | Path, *, title: str = "") -> Path:
    """Write ``power.png``: per candidate, the power of the test (share of pseudo-real
    replicates whose gap lies above the noise floor) against the effect's strength (its
    distance from off in the search coordinate, on a square-root axis, so off is at the left also
    where its value is at infinity, as clumping's and nonlinearity's; the ticks give the values), with 95 % Wilson
    intervals, the power required (dashed), the detection limit (dotted) and the test value (grey).

    Parameters
    ----------
    curve, limits : DataFrame
        ``detection_curve.csv`` and ``detection_limits.csv`` (:func:`.power.detection_limits`).
    path : path
        PNG written (atomically).
    """
    plt = pyplot()
    names = list(dict.fromkeys(curve["effect"])) if len(curve) else []
    n = max(len(names), 1)
    cols = min(n, 5)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.4 * rows + 0.6), squeeze=False,
                             layout="constrained")
    for ax in axes.flat[len(names):]:
        ax.set_axis_off()
    if not names:
        axes[0, 0].text(0.5, 0.5, "no candidate", ha="center", va="center", transform=axes[0, 0].transAxes)
    for ax, name in zip(axes.flat, names):
        c = curve[curve["effect"] == name].sort_values("strength")
        v = c["strength"].to_numpy(float)
        u0 = cat.to_u(name, cat.effect(name).off)

        def at(value, name=name, u0=u0):  # a value's strength
            return abs(cat.to_u(name, float(value)) - u0)

        # a square-root axis: the walk's steps towards the limit lie far below the test value
        ax.set_xscale("function", functions=(lambda x: np.sqrt(np.clip(x, 0.0, None)), np.square))
        ax.set_xticks(v, ["off"] + [f"{x:.3g}" for x in c["value"].to_numpy(float)[1:]])
        p = c["power"].to_numpy(float)
        lo = c["power_ci_low"].to_numpy(float) if "power_ci_low" in c else p
        hi = c["power_ci_high"].to_numpy(float) if "power_ci_high" in c else p
        ax.errorbar(v, p, yerr=np.vstack([np.clip(p - lo, 0, None), np.clip(hi - p, 0, None)]), marker="o",
                    color=NAMED_COLOUR, capsize=3, linewidth=1)
        lim = limits[limits["effect"] == name]
        if len(lim):
            r = lim.iloc[0]
            ax.axhline(float(r["power"]), color="k", linestyle="--", linewidth=0.8)
            if "test_value" in lim:
                ax.axvline(at(r["test_value"]), color=OTHER_COLOUR, linewidth=2, zorder=0)  # behind its rung
            if np.isfinite(float(r["smallest_detectable"])):
                ax.axvline(at(r["smallest_detectable"]), color=AFTER_COLOUR, linestyle=":", linewidth=1.5)
                # the limit's interval, in strength: an infinite value is off (an inverse scale's),
                # an end beyond the strongest value tried (NaN) runs to the edge
                edge = v[-1] * 1.05
                ends = [0.0 if np.isinf(x) else edge if np.isnan(x) else at(x)
                        for x in (float(r.get("limit_ci_low", np.nan)), float(r.get("limit_ci_high", np.nan)))]
                if not all(e == edge for e in ends):
                    ax.axvspan(min(ends), max(ends), color=AFTER_COLOUR, alpha=0.15, linewidth=0)
            unit = str(r["unit"])
        else:
            unit = ""
        ax.set_xlim(0.0, v[-1] * 1.1)
        ax.set_ylim(-0.03, 1.03)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(unit, fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes[:, 0]:
        ax.set_ylabel("power", fontsize=8)
    reps = int(curve["replicates"].iloc[0]) if len(curve) else 0
    fig.suptitle((title + "\n" if title else "") + f"power per value, off at the left, distance from off on a square-root axis ({reps} pseudo-real replicates, 95 % Wilson "
                 "intervals); dashed: power required, dotted: limit (shaded: its 95 % interval), grey: test value", fontsize=9)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
