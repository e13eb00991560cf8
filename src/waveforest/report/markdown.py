"""Plain Markdown (pipe) tables from DataFrames, without extra dependencies."""

from __future__ import annotations

import numpy as np
import pandas as pd


def format_value(value, digits: int = 3) -> str:
    """A cell as text: integers as is, floats with ``digits`` significant decimals, NaN empty."""
    if value is None:
        return ""
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value):
            return ""
        if value == int(value) and abs(value) < 1e6:
            return f"{value:.1f}" if digits else str(int(value))
        mag = abs(value)
        if mag >= 100:
            return f"{value:.1f}"
        if mag >= 10:
            return f"{value:.2f}"
        return f"{value:.{digits}f}"
    return str(value).replace("|", "\\|")


def to_markdown(df: pd.DataFrame, digits: int = 3) -> str:
    """A GitHub-style pipe table of ``df`` (index dropped)."""
    header = "| " + " | ".join(str(c) for c in df.columns) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    lines = [header, rule]
    for row in df.itertuples(index=False):
        lines.append("| " + " | ".join(format_value(v, digits) for v in row) + " |")
    return "\n".join(lines) + "\n"
