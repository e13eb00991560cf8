"""Physical constants, grids, numerical tolerances and fixed names shared by every module.

One place for every epsilon and offset (STYLE.md), so that kernels and tests agree.
"""

C_M_PER_S = 299_792_458.0
"""Speed of light in vacuum, m/s. Air (n ~ 1.0003) is ignored, as in the ALS60 ranges."""

C_M_PER_NS = C_M_PER_S * 1e-9
"""Speed of light, m/ns."""

RANGE_PER_NS = C_M_PER_NS / 2.0
"""One-way range per nanosecond of two-way time, m/ns (0.1499 m/ns)."""

BIN_NS = 0.05
"""Fine time grid of sigma(t) and S(t), ns of two-way time (docs/method.md §(c), d): 0.75 cm of range."""

RAY_EPS_M = 1e-4
"""Offset of a new ray origin from the surface it leaves, m (float32 Embree scenes near the origin)."""

RECORD_NS = 256.0
"""ALS60 waveform record length, ns (docs/method.md §(a))."""

KIND_GROUND, KIND_LEAF, KIND_WOOD, KIND_OTHER = 0, 1, 2, 3
"""Scene element kinds (per-triangle ``kind`` in scenes and PLY files)."""

KIND_NAMES = {KIND_GROUND: "ground", KIND_LEAF: "leaf", KIND_WOOD: "wood", KIND_OTHER: "other"}

FUNCTIONAL_GROUPS = ("conifer", "broadleaf", "low_green", "low_barren_abiotic")
"""The four functional groups of docs/method.md §(i4), in the paper's order."""
