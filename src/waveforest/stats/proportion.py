"""Intervals of a proportion."""

from __future__ import annotations

import math


def wilson_interval(p: float, n: int, z: float = 1.959964) -> tuple[float, float]:
    """Wilson score interval of a proportion ``p`` observed on ``n`` independent trials (95 % by
    default); (nan, nan) for n < 1."""
    if n < 1 or not math.isfinite(p):
        return math.nan, math.nan
    d = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return max(0.0, centre - half), min(1.0, centre + half)
