"""LAS 1.3/1.4 waveform files: the public API of the reader, the writer and the summary.

Reading (``waveforest ingest``)::

    from waveforest.io.las import read_waveform_las, WaveformPulseReader, las_to_pulses
    table = read_waveform_las("line.las")                 # small files: one pulse table
    for batch in WaveformPulseReader("big.las"):          # any size: pulse-table batches
        ...
    las_to_pulses("big.las", "big.parquet")               # any size: streamed into Parquet

Writing (the virtual campaign, tests)::

    from waveforest.io.las import write_waveform_las, WaveformLasWriter
    write_waveform_las("line.las", pulses, version="1.4", bits=8, storage="internal")
    with WaveformLasWriter("big.las", storage="external") as w:   # streaming
        for chunk in chunks:
            w.write(chunk)

Modules:

- :mod:`~waveforest.io.las.format`: byte layouts (header, (E)VLRs, point formats 4, 5, 9, 10,
  wave packet descriptors), the errors and warnings.
- :mod:`~waveforest.io.las.file`: :func:`open_waveform_las`, the checks of a file's header,
  VLRs and waveform data before any point is read.
- :mod:`~waveforest.io.las.points`: point records -> compact records, grouped into pulses.
- :mod:`~waveforest.io.las.gather`: waveform packets decoded from the waveform data.
- :mod:`~waveforest.io.las.read`: points and packets -> pulse tables (conventions: pulse
  grouping, geometry, AGC, memory).
- :mod:`~waveforest.io.las.pulses`: a LAS file streamed into a Parquet pulse table, the
  sensor locator (trajectory, nominal range).
- :mod:`~waveforest.io.las.write`: pulse tables -> LAS files.
- :mod:`~waveforest.io.las.info`: a lasinfo-style summary.
"""

from waveforest.io.las.file import LasWaveformFile, WaveformData, find_wdp, open_waveform_las
from waveforest.io.las.format import LasWaveformError, LasWaveformWarning, WavePacketDescriptor
from waveforest.io.las.info import LasSummary, format_summary, summarise
from waveforest.io.las.pulses import IngestResult, las_to_pulses, sensor_locator
from waveforest.io.las.read import ReadStats, WaveformPulseReader, read_waveform_las
from waveforest.io.las.write import GEOMETRY_TOL_M, WaveformLasWriter, write_waveform_las

__all__ = [
    "GEOMETRY_TOL_M",
    "IngestResult",
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
    "las_to_pulses",
    "open_waveform_las",
    "read_waveform_las",
    "sensor_locator",
    "summarise",
    "write_waveform_las",
]
