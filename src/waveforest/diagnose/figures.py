"""The diagnosis figure ``gap.png``: the gap before and after, and the candidates' evidence."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from waveforest.atomic import atomic_path
from waveforest.plotting import pyplot

BEFORE_COLOUR, AFTER_COLOUR = "#7f7f7f", "#c55a11"
NAMED_COLOUR, OTHER_COLOUR = "#1f4e79", "#bfbfbf"


def gap_figure(gap: pd.DataFrame, candidates: pd.DataFrame, path: str | Path, *, title: str = "") -> Path:
    """Write ``gap.png``.

    Left: the moment gap per feature and in total, base model ("before") and extended model
    ("after"), with their bootstrap intervals and the base model's noise floor (a tick per
    bar). Right: every candidate's test-half gap reduction with its interval, per round
    (named ones dark), the evidence on which the effects were named.

    Parameters
    ----------
    gap : DataFrame
        ``gap_before_after.csv`` (:func:`.gap.before_after`): rows with level feature/total.
    candidates : DataFrame
        ``candidates.csv`` (may be empty).
    path : path
        PNG written (atomically).
    title : str
        Figure title (e.g. the verdict).
    """
    plt = pyplot()
    rows = gap[gap["level"].isin(["feature", "total"])].reset_index(drop=True)
    n_c = len(candidates)
    fig, axes = plt.subplots(1, 2, figsize=(11, max(3.6, 0.9 + 0.28 * n_c)),
                             gridspec_kw={"width_ratios": [1.1, 1.0]})
    ax = axes[0]
    x = np.arange(len(rows))
    for off, key, colour, label in ((-0.2, "before", BEFORE_COLOUR, "base model"),
                                    (0.2, "after", AFTER_COLOUR, "with named effects")):
        g = rows[f"gap_{key}"].to_numpy(float)
        lo = rows[f"{key}_ci_low"].to_numpy(float)
        hi = rows[f"{key}_ci_high"].to_numpy(float)
        err = np.vstack([np.clip(g - lo, 0, None), np.clip(hi - g, 0, None)])
        ax.bar(x + off, g, 0.38, color=colour, label=label, yerr=np.nan_to_num(err), capsize=3)
    fl = rows["noise_floor"].to_numpy(float)
    ax.hlines(fl, x - 0.4, x + 0.4, colors="k", linestyles="--", linewidth=1, label="noise floor (base)")
    ax.set_xticks(x, rows["feature"].tolist())
    ax.set_ylabel("moment gap, mean of $\\bar{d}^2 + \\bar{l}^2$ (datasets pooled)")
    ax.set_title("gap between real and simulated features")
    ax.legend(fontsize=8)
    ax = axes[1]
    if n_c:
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
    else:
        ax.text(0.5, 0.5, "no candidate tested", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
