"""The pulse table: one row per laser pulse, for real and simulated pulses alike.

Schema (docs/design.md, "Data contracts"). Times inside a waveform count from its first
sample; sample ``k`` is at ``k * sampling_ns``. Coordinates are those of the LAS file
(projected, metres). Unknown values are NaN, never invented.

========================  ==============  ==========================================
column                    type            meaning
========================  ==============  ==========================================
dataset                   string          dataset name, e.g. ``2010_12_1``
pulse_id                  int64           unique within the dataset
source                    string          ``real`` or ``sim``
gps_time                  float64         s (GPS time of the LAS points)
sensor_x/_y/_z            float64         sensor position at emission, m (NaN if unknown)
dir_x/_y/_z               float64         unit beam direction, sensor -> target
anchor_x/_y/_z            float64         position of the first waveform sample, m
range_m                   float64         sensor -> first DR echo, m (NaN if unknown)
scan_angle_deg            float64         scan angle of the LAS point, degrees
agc                       float64         AGC value (NaN if the data have none)
sampling_ns               float64         waveform sampling interval, ns
digitizer_gain            float64         volts per DN (LAS descriptor)
digitizer_offset          float64         volts at DN 0 (LAS descriptor)
samples                   list<float32>   waveform, DN (AGC-normalised after ``agc``)
n_echoes                  int16           number of DR echoes of the pulse
echo_x/_y/_z              list<float64>   DR echo positions, m, in return order
echo_time_ns              list<float64>   DR echo times from the first sample, ns
echo_intensity            list<float32>   DR echo intensity, DN
========================  ==============  ==========================================

Optional, written by ``survey``: scan_flags (uint8: bit 0 the scan direction flag, bit 1 edge of
flight line, as the LAS point records them) and point_source_id (uint16: the flight line, leg + 1).

After ``select`` a pulse table also has: sample_id (string), species (string),
functional_group (string), ground_z (float64, m: GNSS ground elevation of the sample).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from waveforest.atomic import atomic_path
from waveforest.errors import WaveforestError

_F64, _F32 = pa.float64(), pa.float32()

PULSE_SCHEMA = pa.schema(
    [
        ("dataset", pa.string()),
        ("pulse_id", pa.int64()),
        ("source", pa.string()),
        ("gps_time", _F64),
        ("sensor_x", _F64), ("sensor_y", _F64), ("sensor_z", _F64),
        ("dir_x", _F64), ("dir_y", _F64), ("dir_z", _F64),
        ("anchor_x", _F64), ("anchor_y", _F64), ("anchor_z", _F64),
        ("range_m", _F64),
        ("scan_angle_deg", _F64),
        ("agc", _F64),
        ("sampling_ns", _F64),
        ("digitizer_gain", _F64),
        ("digitizer_offset", _F64),
        ("samples", pa.list_(_F32)),
        ("n_echoes", pa.int16()),
        ("echo_x", pa.list_(_F64)), ("echo_y", pa.list_(_F64)), ("echo_z", pa.list_(_F64)),
        ("echo_time_ns", pa.list_(_F64)),
        ("echo_intensity", pa.list_(_F32)),
    ]
)
"""Arrow schema of a pulse table (minimum columns; later stages append columns)."""

SELECT_FIELDS = [
    pa.field("sample_id", pa.string()),
    pa.field("species", pa.string()),
    pa.field("functional_group", pa.string()),
    pa.field("ground_z", _F64),
]
"""Columns that ``select`` appends to a pulse table."""


class TableError(WaveforestError):
    """A table that does not follow its schema."""


def check_pulses(table: pa.Table, source: str | Path = "<table>") -> pa.Table:
    """Return ``table`` cast to :data:`PULSE_SCHEMA` column types; raise on a missing column."""
    missing = [f.name for f in PULSE_SCHEMA if f.name not in table.column_names]
    if missing:
        raise TableError(f"{source}: pulse table lacks column(s) {', '.join(missing)}")
    cols, fields = [], []
    for f in PULSE_SCHEMA:
        col = table.column(f.name)
        if col.type != f.type:
            try:
                col = col.cast(f.type)
            except (pa.ArrowInvalid, pa.ArrowNotImplementedError) as exc:
                raise TableError(f"{source}: column {f.name} is {col.type}, expected {f.type}") from exc
        cols.append(col)
        fields.append(f)
    for name in table.column_names:  # extra columns (select, features, ...) are kept
        if name not in PULSE_SCHEMA.names:
            cols.append(table.column(name))
            fields.append(table.schema.field(name))
    return pa.Table.from_arrays(cols, schema=pa.schema(fields))


def single_dataset(names: set, path) -> str:
    """The one dataset name of ``names`` (those found in the pulse table at ``path``).

    Raises WaveforestError unless ``names`` holds exactly one name.
    """
    if len(names) != 1:
        raise WaveforestError(
            f"{path}: holds datasets {', '.join(sorted(map(str, names))) or '(none)'}; expected exactly one "
            "(run the step once per dataset file)")
    return next(iter(names))


def read_pulses(path: str | Path, columns: list[str] | None = None) -> pa.Table:
    """Read a pulse table from Parquet and check it against :data:`PULSE_SCHEMA`."""
    path = Path(path)
    if not path.exists():
        raise TableError(f"{path}: no such file")
    try:
        table = pq.read_table(path, columns=columns)
    except (pa.ArrowInvalid, OSError) as exc:
        raise TableError(f"{path}: not a readable Parquet file ({exc})") from exc
    return table if columns is not None else check_pulses(table, path)


def write_table(table: pa.Table, path: str | Path) -> Path:
    """Write any Arrow table to Parquet atomically (zstd)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression="zstd")
    return path


def write_pulses(table: pa.Table, path: str | Path) -> Path:
    """Check ``table`` against the pulse schema and write it to Parquet atomically."""
    return write_table(check_pulses(table, path), path)


_STREAM_OPTIONS = dict(compression="lz4", use_dictionary=["dataset", "source"], write_statistics=False)
"""Parquet options of streamed pulse tables: lz4 compression, dictionaries only for the
``dataset`` and ``source`` strings, no column statistics (the waveform lists are noise-like).
Why these (ingest rates of the alternatives): docs/validation.md, "Speed"."""


def write_pulse_batches(batches: Iterable[pa.Table], path: str | Path) -> int:
    """Stream pulse tables into one Parquet file atomically; return the number of rows.

    Memory stays bounded by the size of one batch. The schema is that of the first
    batch (after :func:`check_pulses`); later batches are cast to it.
    """
    path = Path(path)
    n = 0
    with atomic_path(path) as tmp:
        writer = None
        try:
            for batch in batches:
                batch = check_pulses(batch, path)
                if writer is None:
                    writer = pq.ParquetWriter(tmp, batch.schema, **_STREAM_OPTIONS)
                writer.write_table(batch.cast(writer.schema))
                n += batch.num_rows
            if writer is None:  # no rows: still a valid, empty table
                writer = pq.ParquetWriter(tmp, PULSE_SCHEMA, **_STREAM_OPTIONS)
        finally:
            if writer is not None:
                writer.close()
    return n


def iter_pulses(path: str | Path, batch_rows: int = 65536, columns: list[str] | None = None) -> Iterator[pa.Table]:
    """Iterate over a pulse Parquet file in batches of at most ``batch_rows`` rows.

    Memory is bounded by one batch: Arrow's pre-buffering of column chunks is off (it holds
    every row group read so far, ~300 MB per 800,000 pulses of 256 samples, until the file is
    closed).
    """
    pf = pq.ParquetFile(path, pre_buffer=False)
    for rb in pf.iter_batches(batch_size=batch_rows, columns=columns):
        yield pa.Table.from_batches([rb])


def same_table(a: pa.Table, b: pa.Table) -> bool:
    """Tables equal column by column, NaN equal to NaN (Arrow's ``equals`` says NaN != NaN)."""
    if a.schema != b.schema or a.num_rows != b.num_rows:
        return False
    for name in a.column_names:
        x, y = a.column(name), b.column(name)
        if pa.types.is_floating(x.type):
            if not np.array_equal(x.to_numpy(), y.to_numpy(), equal_nan=True):
                return False
        elif not x.equals(y):
            return False
    return True


def list_to_padded(column: pa.ChunkedArray | pa.Array, fill: float = np.nan, dtype=np.float32) -> tuple[np.ndarray, np.ndarray]:
    """A list column as a padded 2-D array and the row lengths.

    Returns
    -------
    values : (n, max_len) ``dtype``, padded with ``fill``
    lengths : (n,) int64
    """
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks() if column.num_chunks != 1 else column.chunk(0)
    offsets = column.offsets.to_numpy().astype(np.int64)
    offsets = offsets - offsets[0]
    flat = column.flatten().to_numpy(zero_copy_only=False).astype(dtype, copy=False)
    lengths = np.diff(offsets)
    n = len(lengths)
    width = int(lengths.max()) if n else 0
    out = np.full((n, width), fill, dtype=dtype)
    if n and width:
        rows = np.repeat(np.arange(n), lengths)
        cols = np.arange(len(flat)) - np.repeat(offsets[:-1], lengths)
        out[rows, cols] = flat
    return out, lengths


def padded_to_list(values: np.ndarray, lengths: np.ndarray, type_: pa.DataType = _F32) -> pa.ListArray:
    """Inverse of :func:`list_to_padded`: rows of ``values`` cut to ``lengths`` as an Arrow list array."""
    values = np.asarray(values)
    lengths = np.asarray(lengths, dtype=np.int64)
    mask = np.arange(values.shape[1])[None, :] < lengths[:, None] if values.ndim == 2 else None
    flat = values[mask] if mask is not None else values[:0]
    offsets = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), pa.array(flat, type=type_))
