"""Diagnosis of missing effects: where simulation and measurement disagree, and why.

Beyond Hovi & Korpela (2014), docs/method.md §(j); the ``diagnose`` stage
(:mod:`waveforest.stages.diagnose`) reads the inputs and writes the outputs. Modules:

* :mod:`.gap` — the gap of one simulation against the real data (per cell, feature, total);
* :mod:`.before_after` — two simulations against the same real data, paired bootstrap;
* :mod:`.catalogue` — the effects as one-parameter model components (search coordinate, grid);
* :mod:`.optimise` — the 1-D optimiser (parabolic vertex, Brent-like steps);
* :mod:`.replicate_cache` — the search's cache of simulator calls, replicates per seed (common random numbers);
* :mod:`.search` — settings and the search loop (fit on one half, test on the other, name);
* :mod:`.strata` — the pulses compared, selection rules, the stratum under the crowns;
* :mod:`.twins` — the study's simulation chain as ``simulate(pulses, effects, seed)``: simulated twins;
* :mod:`.missing_effects` — the whole diagnosis: search, fresh before/after, signatures, the markdown summary;
* :mod:`.power` — detection limits: the smallest value of each candidate these data would detect;
* :mod:`.figures` — ``gap.png``;
* :mod:`.settings` — :class:`.settings.DiagnoseSettings`, everything read from the config
  (built by :func:`waveforest.settings.diagnose_settings`).
"""
