"""Intervals of a proportion and of a quantile."""

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


def quantile_ranks(n: int, p: float, level: float = 0.95) -> tuple[int, int]:
    """Ranks (r, s), 1-based, of the distribution-free interval [X_(r), X_(s)] of the ``p``-quantile
    from ``n`` independent draws (order statistics X_(1) <= ... <= X_(n)), equal-tailed: each
    tail misses with probability at most (1 - level) / 2, as the number of draws below the
    quantile is Binomial(n, p). r = 0 (s = n + 1): no draw bounds the quantile from below (above)."""
    if n < 1 or not 0.0 < p < 1.0:
        raise ValueError(f"quantile_ranks: need n >= 1 and 0 < p < 1, got n={n}, p={p}")
    tail = (1.0 - level) / 2.0
    pmf = [math.comb(n, i) * p**i * (1.0 - p) ** (n - i) for i in range(n + 1)]
    below = 0.0  # P(B <= r - 1)
    r = 0
    while r < n and below + pmf[r] <= tail:
        below += pmf[r]
        r += 1
    above = 0.0  # P(B >= s)
    s = n + 1
    while s > 1 and above + pmf[s - 1] <= tail:
        above += pmf[s - 1]
        s -= 1
    return r, s


def strongest_tried(upper_bound: float, test_value: float, power_at_bound: float) -> float:
    """The strongest value a detection limit's walk tried, from its row of
    :data:`waveforest.diagnose.power.LIMIT_COLUMNS`: the range's bound where it was tried (its
    power is not NaN), else the test value (NaN in a table without one: the bound)."""
    return upper_bound if not math.isnan(power_at_bound) or math.isnan(test_value) else test_value


def limit_interval(low: float, high: float, strongest: float) -> str:
    """A detection limit's interval as text (``limit_ci_low``, ``limit_ci_high`` of
    :data:`waveforest.diagnose.power.LIMIT_COLUMNS`, and :func:`strongest_tried`): ``[1.9, 3.2]``,
    or ``[1.9, > 2.5]`` when its end on the side of the strongest value tried lies beyond it
    (NaN); "" when both are NaN."""
    if math.isnan(low) and math.isnan(high):
        return ""
    lo = f"< {strongest:.3g}" if math.isnan(low) else f"{low:.3g}"
    hi = f"> {strongest:.3g}" if math.isnan(high) else f"{high:.3g}"
    return f"[{lo}, {hi}]"
