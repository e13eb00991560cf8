"""Input and output: LAS waveform packets and the tables of the pipeline.

Modules:

- :mod:`waveforest.io.las`: LAS 1.3/1.4 waveform files (read, write, summarise).
- :mod:`waveforest.io.pulses`: the pulse table (Parquet), its schema and readers/writers.
- :mod:`waveforest.io.tables`: the campaign CSV tables (datasets, fields, targets), one
  checked reader each.
- :mod:`waveforest.io.trajectory`: sensor trajectories (CSV) and pulse locators.
- :mod:`waveforest.io.paper`: the paper's published tables (Hovi & Korpela 2014).
- :mod:`waveforest.io.csvfile`: the CSV opener the table readers share.
"""
