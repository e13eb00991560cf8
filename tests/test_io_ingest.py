"""``waveforest.io.las.pulses.las_to_pulses``: the LAS -> pulse table streaming behind ``waveforest ingest``."""

import numpy as np
import pyarrow.parquet as pq
import pytest
from fixtures.pulses import synthetic_pulses
from test_io_las_roundtrip import assert_round_trip, assert_tables_equal

from waveforest.errors import WaveforestError
from waveforest.io.las import LasWaveformWarning, read_waveform_las, summarise, write_waveform_las
from waveforest.io.las.pulses import las_to_pulses as run
from waveforest.io.pulses import PULSE_SCHEMA, read_pulses


def test_run_writes_the_pulse_table(tmp_path):
    t = synthetic_pulses(500, seed=61, n_samples=(128, 256), max_echoes=4)
    las = write_waveform_las(tmp_path / "2010_12_1.las", t, version="1.3", point_format=4)
    out = tmp_path / "pulses" / "2010_12_1.parquet"
    res = run(las, out, batch_pulses=128, nominal_range_m=900.0)
    assert (res.out, res.n_pulses, res.n_points, res.sensor) == (out, 500, int(t["n_echoes"].to_numpy().sum()), "nominal")
    assert res.agc_attribute == "user_data" and res.n_without_waveform == 0
    back = read_pulses(out)
    assert back.schema.equals(PULSE_SCHEMA)
    assert set(back["dataset"].to_pylist()) == {"2010_12_1"}
    assert pq.ParquetFile(out).metadata.num_row_groups == 4  # streamed in batches of 128
    assert_round_trip(t, back)
    np.testing.assert_array_equal(back["range_m"].to_numpy(), 900.0)
    assert "500 pulses" in res.summary()


def test_run_on_a_large_file_uses_bounded_buckets(tmp_path):
    t = synthetic_pulses(2500, seed=62)
    las = write_waveform_las(tmp_path / "a.las", t, storage="external")
    out = tmp_path / "a.parquet"
    res = run(las, out, bucket_points=1000, chunk_points=400, dataset="d")
    assert res.n_pulses == 2500
    assert_tables_equal(read_pulses(out), read_waveform_las(las, dataset="d"))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.las", "a.parquet", "a.wdp"]  # spill removed
    # info counts the same through buckets
    small, whole = summarise(las, bucket_points=1000, chunk_points=400), summarise(las)
    assert (small.n_pulses, small.n_packets, small.returns_by_number) == (whole.n_pulses, whole.n_packets, whole.returns_by_number)
    assert small.n_pulses == 2500


def test_empty_file(tmp_path):
    las = write_waveform_las(tmp_path / "empty.las", synthetic_pulses(0))
    with pytest.warns(LasWaveformWarning, match="announces 0 points"):
        res = run(las, tmp_path / "e.parquet")
    assert res.n_pulses == 0 and read_pulses(tmp_path / "e.parquet").num_rows == 0


def test_trajectory_and_nominal_range_exclude_each_other(tmp_path):
    las = write_waveform_las(tmp_path / "x.las", synthetic_pulses(3))
    with pytest.raises(WaveforestError, match="either a trajectory or a nominal range"):
        run(las, tmp_path / "x.parquet", trajectory=tmp_path / "t.csv", nominal_range_m=10.0)
    with pytest.raises(WaveforestError, match="overwrite the input"):
        run(las, las)
    ext = write_waveform_las(tmp_path / "y.las", synthetic_pulses(3), storage="external")
    wdp = (tmp_path / "y.wdp").read_bytes()
    (tmp_path / "link.parquet").symlink_to(tmp_path / "y.wdp")
    for out in ("y.wdp", "link.parquet"):  # its waveform file, by name or through a link
        with pytest.raises(WaveforestError, match="overwrite the input y.wdp"):
            run(ext, tmp_path / out)
    assert (tmp_path / "y.wdp").read_bytes() == wdp
