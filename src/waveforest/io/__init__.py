"""Input and output: LAS waveform packets and the Parquet tables of the pipeline."""
