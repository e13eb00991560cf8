"""The search's simulation cache: one simulator call per (half, model), common random numbers.

A *simulator* is ``simulate(pulses, effects, seed) -> feature table`` (:data:`Simulator`).
:class:`SimulationCache` holds the pulses of each half of the field samples
(:data:`HALVES`) and one seed per half; ``get(half, effects)`` simulates that half under
``effects`` once (``replicates`` calls, replicate r with the seed ``named_seed("replicate", seed, r)``)
and keeps the concatenated feature table, keyed by the half and the effects rounded to 12
decimals (:func:`effects_key`). The same seed for every model of a half gives common random numbers
(docs/method.md §(j), the search). Errors: :class:`waveforest.errors.WaveforestError` when
the simulator returns no DataFrame.
"""

from __future__ import annotations

from collections.abc import Callable

import pandas as pd

from waveforest.errors import WaveforestError
from waveforest.rng import named_seed

Simulator = Callable[[pd.DataFrame, dict, int], pd.DataFrame]
"""``simulate(pulses, effects, seed) -> feature table``: one row per simulated pulse with
dataset, sample_id, species and the feature columns. ``pulses`` is a subset of the search's
pulse table (rows kept whole, plus a ``replicate`` column); the same seed must give the same
random numbers whatever the effect values (common random numbers)."""

HALVES = ("A", "B")
"""Names of the two halves of the field samples."""


def effects_key(effects: dict[str, float]) -> tuple:
    """A hashable key of ``effects``: sorted (name, value rounded to 12 decimals) pairs."""
    return tuple(sorted((k, round(float(v), 12)) for k, v in effects.items()))


class SimulationCache:
    """Cache of simulator calls keyed by (half, effects); one seed per half."""

    def __init__(self, simulate: Simulator, halves: dict[str, pd.DataFrame], seeds: dict[str, int],
                 replicates: int, progress: Callable[[str], None] | None):
        self.simulate = simulate
        self.halves = halves
        self.seeds = seeds
        self.replicates = replicates
        self.progress = progress
        self.cache: dict = {}
        self.calls = 0

    def get(self, half: str, effects: dict[str, float]) -> pd.DataFrame:
        """Simulated features of ``half`` under ``effects`` (all replicates, cached)."""
        key = (half, effects_key(effects))
        if key not in self.cache:
            self.cache[key] = simulate_all(self.simulate, self.halves[half], effects, self.seeds[half],
                                           self.replicates)
            self.calls += 1
            if self.progress is not None:
                self.progress(f"{half} {dict(effects)}")
        return self.cache[key]

    def has(self, effects: dict[str, float]) -> bool:
        """Whether every half with pulses is already simulated under ``effects``."""
        return all((h, effects_key(effects)) in self.cache for h in HALVES if len(self.halves[h]))

    def all(self, effects: dict[str, float]) -> pd.DataFrame:
        """Simulated features of all samples (both halves) under ``effects``."""
        return pd.concat([self.get(h, effects) for h in HALVES if len(self.halves[h])], ignore_index=True)


def simulate_all(simulate: Simulator, keys: pd.DataFrame, effects: dict, seed: int, replicates: int) -> pd.DataFrame:
    """All of ``keys`` simulated under ``effects`` in one go (no halves, no cache): replicate r
    with the seed ``named_seed("replicate", seed, r)`` (:mod:`waveforest.rng`), as
    :meth:`SimulationCache.get` draws them."""
    parts = []
    for r in range(replicates):
        s = named_seed("replicate", seed, r)
        out = simulate(keys.assign(replicate=r), dict(effects), s)
        if not isinstance(out, pd.DataFrame):
            raise WaveforestError("diagnose: the simulator must return a pandas DataFrame")
        parts.append(out)
    return pd.concat(parts, ignore_index=True)
