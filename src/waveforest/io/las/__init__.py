"""LAS 1.3/1.4 waveform files: the public API of the reader, the writer and the summary.

Reading (``waveforest ingest``)::

    from waveforest.io.las import read_waveform_las, WaveformPulseReader
    table = read_waveform_las("line.las")                 # small files: one pulse table
    for batch in WaveformPulseReader("big.las"):          # any size: pulse-table batches
        ...

Writing (the virtual campaign, tests)::

    from waveforest.io.las import write_waveform_las, WaveformLasWriter
    write_waveform_las("line.las", pulses, version="1.4", bits=8, storage="internal")
    with WaveformLasWriter("big.las", storage="external") as w:   # streaming
        for chunk in chunks:
            w.write(chunk)

Conventions (pulse grouping, geometry, AGC, memory) are documented in :mod:`.las_read`
and :mod:`.las_write`; the byte layouts in :mod:`.las_format`.
"""

from waveforest.io.las.file import LasWaveformFile, WaveformData, find_wdp, open_waveform_las
from waveforest.io.las.format import LasWaveformError, LasWaveformWarning, WavePacketDescriptor
from waveforest.io.las.info import LasSummary, format_summary, summarise
from waveforest.io.las.read import ReadStats, WaveformPulseReader, read_waveform_las
from waveforest.io.las.write import GEOMETRY_TOL_M, WaveformLasWriter, write_waveform_las

__all__ = [
    "GEOMETRY_TOL_M",
    "LasSummary",
    "LasWaveformError",
    "LasWaveformFile",
    "LasWaveformWarning",
    "ReadStats",
    "WavePacketDescriptor",
    "WaveformData",
    "WaveformLasWriter",
    "WaveformPulseReader",
    "find_wdp",
    "format_summary",
    "open_waveform_las",
    "read_waveform_las",
    "summarise",
    "write_waveform_las",
]
