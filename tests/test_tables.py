"""Pulse-table helpers: padding round trip, schema check, streaming writer."""

import numpy as np
import pyarrow as pa
import pytest

from waveforest.io import pulses as tables


def test_padded_list_round_trip():
    rng = np.random.default_rng(0)
    lengths = rng.integers(0, 9, 40)
    values = np.full((40, 8), np.nan, np.float32)
    for i, n in enumerate(lengths):
        values[i, :n] = rng.normal(size=n)
    arr = tables.padded_to_list(values, lengths)
    back, back_len = tables.list_to_padded(arr)
    np.testing.assert_array_equal(back_len, lengths)
    np.testing.assert_array_equal(back[:, : back.shape[1]], values[:, : back.shape[1]])


def _empty_pulses(n):
    cols = {}
    for f in tables.PULSE_SCHEMA:
        if pa.types.is_list(f.type):
            cols[f.name] = pa.array([[1.0]] * n, type=f.type)
        elif pa.types.is_string(f.type):
            cols[f.name] = pa.array(["x"] * n)
        else:
            cols[f.name] = pa.array(np.arange(n), type=f.type)
    return pa.table(cols)


def test_missing_column_is_named(tmp_path):
    t = _empty_pulses(3).drop(["agc"])
    with pytest.raises(tables.TableError, match="agc"):
        tables.write_pulses(t, tmp_path / "p.parquet")
    assert not list(tmp_path.iterdir())


def test_streamed_batches_equal_one_table(tmp_path):
    t = _empty_pulses(10)
    n = tables.write_pulse_batches([t.slice(0, 4), t.slice(4, 6)], tmp_path / "p.parquet")
    assert n == 10
    back = tables.read_pulses(tmp_path / "p.parquet")
    assert back.num_rows == 10
    assert back.column("pulse_id").to_pylist() == list(range(10))
