"""The pipeline stages: one module per CLI subcommand and Snakemake rule (docs/design.md).

Each module holds its click command, a ``run()`` that reads the inputs, calls the pure code
of the lower packages and writes the outputs atomically, and nothing else of substance.
In pipeline order:

- :mod:`.synthesize` -- the virtual campaign; :mod:`.ingest` -- LAS -> pulse table;
  :mod:`.info` -- what a LAS file holds;
- :mod:`.agc` -- Eq. 1 fit and normalisation (docs/method.md §(b)); :mod:`.calibrate` -- S(t), noise, CFD (§(e), §(f));
- :mod:`.select` -- the pulses of the field samples; :mod:`.features` -- waveform features (§(h));
- :mod:`.vegetation`, :mod:`.trace` -- a plant (§(g)) and its sigma(t) (§(d));
- :mod:`.simulate` -- the simulated twins (§(i1)); :mod:`.compare` -- real vs simulated;
- :mod:`.classify` -- LDA (§(i4)); :mod:`.sensitivity`, :mod:`.sensor_study` -- the studies (§(i2), §(i3));
- :mod:`.diagnose` -- the missing effects (§(j)); :mod:`.report` -- the report.
"""
