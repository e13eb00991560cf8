"""Plain Markdown (pipe) tables from DataFrames, without extra dependencies."""

from __future__ import annotations

import numpy as np
import pandas as pd

NO_VALUE = "—"
"""A cell without a value (the summary adds the reason: ``— (reason)``)."""


def format_value(value, digits: int = 3) -> str:
    """A cell as text: integers as is, floats with ``digits`` significant decimals; no value
    (None, NaN, empty text) is ``—``, never an empty cell."""
    if value is None:
        return NO_VALUE
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        if np.isnan(value):
            return NO_VALUE
        if np.isinf(value):
            return "inf" if value > 0 else "-inf"
        if value == int(value) and abs(value) < 1e6:
            return f"{value:.1f}" if digits else str(int(value))
        mag = abs(value)
        if mag >= 100:
            return f"{value:.1f}"
        if mag >= 10:
            return f"{value:.2f}"
        return f"{value:.{digits}f}"
    text = str(value).replace("|", "\\|").replace("\n", " ")
    return text if text.strip() else NO_VALUE


def to_markdown(df: pd.DataFrame, digits: int = 3) -> str:
    """A GitHub-style pipe table of ``df`` (index dropped)."""
    header = "| " + " | ".join(str(c) for c in df.columns) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    lines = [header, rule]
    for row in df.itertuples(index=False):
        lines.append("| " + " | ".join(format_value(v, digits) for v in row) + " |")
    return "\n".join(lines) + "\n"
