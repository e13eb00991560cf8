"""The paper's tables shipped with the package (``resources/paper/``), to show beside ours."""

from __future__ import annotations

import pandas as pd

from waveforest import RESOURCES

PAPER_DIR = RESOURCES / "paper"
"""Folder of the copies of Hovi & Korpela (2014) Tables 3 and 4 and the Fig. 9 findings."""


def table3() -> pd.DataFrame:
    """Table 3: dataset, species, feature, sim_mean, sim_sd, real_mean, real_sd, delta_pct."""
    return pd.read_csv(PAPER_DIR / "table3_sim_vs_real.csv")


def table3_counts() -> pd.DataFrame:
    """Table 3 pulse counts: dataset, species, N."""
    return pd.read_csv(PAPER_DIR / "table3_counts.csv")


def table4() -> pd.DataFrame:
    """Table 4: dataset, one_pulse_correct_pct, one_pulse_kappa, mean_of_sample_correct_pct,
    mean_of_sample_kappa, pulses_per_sample."""
    return pd.read_csv(PAPER_DIR / "table4_classification.csv")


def fig9_trend() -> pd.DataFrame:
    """Fig. 9 findings: parameter (footprint_m, pulse_width_ns, sampling_ns), low, high, unit, claim.

    For ``footprint_m``, [low, high] is the footprint up to which accuracy improves (0.30-0.36 m).
    """
    return pd.read_csv(PAPER_DIR / "fig9_trend.csv")
