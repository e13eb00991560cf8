"""Write synthetic pulse tables as LAS waveform files and read them back.

Truth is the table we wrote: samples identical, echo times to float32-ps precision, echo
coordinates to the header quantisation, anchors and directions from the LAS relation.
"""

import hashlib

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pytest
from fixtures.pulses import synthetic_pulses
from reference_io import reference_pulses

from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.las import WaveformPulseReader, open_waveform_las, read_waveform_las
from waveforest.io.las.write import WaveformLasWriter, creation_today, write_waveform_las

TIME_TOL_NS = 1e-5
"""Echo times are stored as float32 ps: 256 ns = 2.56e5 ps has a float32 step of 0.016 ps."""
DIR_TOL = 1e-6
"""x(t), y(t), z(t) are float32: relative precision 6e-8, doubled for the normalisation."""


def _flat(table, col):
    return np.concatenate(table[col].to_numpy(zero_copy_only=False)).astype(np.float64)


def _xyz(table, prefix):
    return np.stack([table[f"{prefix}{c}"].to_numpy() for c in "xyz"], axis=1)


def assert_tables_equal(a: pa.Table, b: pa.Table):
    """Same schema and values (NaN equal to NaN)."""
    assert a.schema == b.schema and a.num_rows == b.num_rows
    for name in a.column_names:
        x, y = a[name].combine_chunks(), b[name].combine_chunks()
        if pa.types.is_list(x.type):
            np.testing.assert_array_equal(x.offsets.to_numpy() - x.offsets[0].as_py(), y.offsets.to_numpy() - y.offsets[0].as_py(), err_msg=name)
            x, y = x.flatten(), y.flatten()
        if pa.types.is_string(x.type):
            assert x.equals(y), name
        else:
            np.testing.assert_array_equal(x.to_numpy(), y.to_numpy(), err_msg=name)  # NaN == NaN here


def assert_round_trip(orig: pa.Table, back: pa.Table, scale: float = 0.001, agc_exact: bool = True):
    assert back.num_rows == orig.num_rows
    np.testing.assert_array_equal(back["gps_time"].to_numpy(), orig["gps_time"].to_numpy())
    assert back["samples"].to_pylist() == orig["samples"].to_pylist()
    np.testing.assert_array_equal(back["sampling_ns"].to_numpy(), orig["sampling_ns"].to_numpy())
    np.testing.assert_array_equal(back["digitizer_gain"].to_numpy(), orig["digitizer_gain"].to_numpy())
    np.testing.assert_array_equal(back["digitizer_offset"].to_numpy(), orig["digitizer_offset"].to_numpy())
    np.testing.assert_array_equal(back["n_echoes"].to_numpy(), orig["n_echoes"].to_numpy())
    np.testing.assert_allclose(_flat(back, "echo_time_ns"), _flat(orig, "echo_time_ns"), rtol=0, atol=TIME_TOL_NS)
    for c in "xyz":  # quantised to the scale: error <= scale / 2
        assert np.max(np.abs(_flat(back, f"echo_{c}") - _flat(orig, f"echo_{c}"))) <= scale / 2 + 1e-9
    np.testing.assert_array_equal(_flat(back, "echo_intensity"), _flat(orig, "echo_intensity"))
    np.testing.assert_allclose(_xyz(back, "dir_"), _xyz(orig, "dir_"), rtol=0, atol=DIR_TOL)
    # anchor = P1 + L1 d: within one quantisation error of P1 plus the float32 L, d error
    miss = np.linalg.norm(_xyz(back, "anchor_") - _xyz(orig, "anchor_"), axis=1)
    assert miss.max() <= np.sqrt(3) * scale / 2 + 1e-6
    if agc_exact:
        np.testing.assert_array_equal(back["agc"].to_numpy(), orig["agc"].to_numpy())
    assert set(back["source"].to_pylist()) == {"real"}


LAYOUTS = [
    ("1.4", 9, 8, "internal"),
    ("1.4", 9, 16, "external"),
    ("1.4", 10, 16, "internal"),
    ("1.4", 4, 8, "external"),
    ("1.3", 4, 8, "internal"),
    ("1.3", 4, 16, "external"),
    ("1.3", 5, 16, "internal"),
    ("1.3", 5, 8, "external"),
]


@pytest.mark.parametrize("version, fmt, bits, storage", LAYOUTS)
def test_round_trip_every_layout(tmp_path, version, fmt, bits, storage):
    t = synthetic_pulses(300, seed=fmt + bits, bits=bits, n_samples=(60, 120, 256), max_echoes=4)
    path = write_waveform_las(tmp_path / "a.las", t, version=version, point_format=fmt, bits=bits, storage=storage)
    assert (tmp_path / "a.wdp").exists() == (storage == "external")
    back = read_waveform_las(path)
    assert_round_trip(t, back)
    assert set(back["dataset"].to_pylist()) == {"a"}
    # the independent struct-based reference reads the same file the same way
    ref = reference_pulses(path)
    assert [p["samples"] for p in ref] == back["samples"].to_pylist()
    np.testing.assert_allclose([p["anchor"] for p in ref], _xyz(back, "anchor_"), rtol=0, atol=1e-9)


@pytest.mark.parametrize("version, fmt, bits, storage", LAYOUTS)
def test_laspy_reads_what_we_write(tmp_path, version, fmt, bits, storage):
    t = synthetic_pulses(120, seed=3, bits=bits, n_samples=(60, 256))
    path = write_waveform_las(tmp_path / "b.las", t, version=version, point_format=fmt, bits=bits, storage=storage)
    las = laspy.read(path)
    n_echo = t["n_echoes"].to_numpy()
    assert str(las.header.version) == version and las.header.point_format.id == fmt
    assert las.header.point_count == n_echo.sum() == len(las.points)
    assert las.header.global_encoding.waveform_data_packets_external == (storage == "external")
    assert las.header.global_encoding.waveform_data_packets_internal == (storage == "internal")
    np.testing.assert_allclose(las.x, _flat(t, "echo_x"), atol=0.0005 + 1e-9)
    np.testing.assert_allclose(las.z, _flat(t, "echo_z"), atol=0.0005 + 1e-9)
    np.testing.assert_array_equal(las.gps_time, np.repeat(t["gps_time"].to_numpy(), n_echo))
    np.testing.assert_array_equal(las.return_number, np.concatenate([np.arange(1, k + 1) for k in n_echo]))
    np.testing.assert_array_equal(las.number_of_returns, np.repeat(n_echo, n_echo))
    np.testing.assert_array_equal(las.user_data, np.repeat(t["agc"].to_numpy(), n_echo))
    np.testing.assert_allclose(las.return_point_wave_location, _flat(t, "echo_time_ns") * 1000, rtol=1e-7)
    # header bounds and counts describe the data
    np.testing.assert_allclose(las.header.mins, [las.x.min(), las.y.min(), las.z.min()])
    np.testing.assert_allclose(las.header.maxs, [las.x.max(), las.y.max(), las.z.max()])
    counts = np.bincount(np.asarray(las.return_number), minlength=16)[1:]
    np.testing.assert_array_equal(las.header.number_of_points_by_return[: len(counts)][:5], counts[:5])
    wpd = [v for v in las.header.vlrs if 100 <= v.record_id <= 354]
    assert sorted({v.parsed_record.number_of_samples for v in wpd}) == [60, 256]
    assert {v.parsed_record.bits_per_sample for v in wpd} == {bits}
    # the spec relation: packet bytes = samples * bytes per sample, packets inside the waveform data
    sizes = np.asarray(las.wavepacket_size)
    ns = {v.record_id - 99: v.parsed_record.number_of_samples for v in wpd}
    np.testing.assert_array_equal(sizes, [ns[i] * bits // 8 for i in np.asarray(las.wavepacket_index)])
    assert np.asarray(las.wavepacket_offset).min() == 60


def test_leica_als60_layout(tmp_path):
    """LAS 1.3 point format 4, 8-bit, 256 samples at 1 and 2 ns (real Leica ALS files)."""
    for sampling in (1.0, 2.0):
        t = synthetic_pulses(400, seed=int(sampling), bits=8, n_samples=256, sampling_ns=sampling)
        path = write_waveform_las(tmp_path / f"leica_{sampling:g}.las", t, version="1.3", point_format=4, bits=8)
        las = open_waveform_las(path)
        assert (las.version, las.point_format, las.record_length) == ("1.3", 4, 57)
        (d,) = las.descriptors.values()
        assert (d.bits, d.n_samples, d.spacing_ps) == (8, 256, int(sampling * 1000))
        assert_round_trip(t, read_waveform_las(path))


def test_geometry_reproduces_each_return_below_1mm(tmp_path):
    """anchor + dir * t * RANGE_PER_NS reproduces each return's XYZ to < 1 mm (LAS relation).

    At a 0.1 mm scale the quantisation (<= 0.09 mm per point) leaves room to check the
    relation itself; at 1 mm the error stays within the quantisation bound.
    """
    t = synthetic_pulses(500, seed=11, max_echoes=5, altitude_m=2500.0)
    for scale, bound in ((0.0001, 0.001), (0.001, np.sqrt(3) * 0.001)):
        path = write_waveform_las(tmp_path / f"g{scale}.las", t, scales=(scale,) * 3)
        back = read_waveform_las(path)
        n = back["n_echoes"].to_numpy()
        p = np.repeat(np.arange(back.num_rows), n)
        model = _xyz(back, "anchor_")[p] + _xyz(back, "dir_")[p] * (_flat(back, "echo_time_ns") * RANGE_PER_NS)[:, None]
        xyz = np.stack([_flat(back, f"echo_{c}") for c in "xyz"], axis=1)
        miss = np.linalg.norm(model - xyz, axis=1)
        assert miss.max() < bound
        # and against the truth of the table we wrote
        truth = np.stack([_flat(t, f"echo_{c}") for c in "xyz"], axis=1)
        assert np.linalg.norm(model - truth, axis=1).max() < bound


def test_same_table_gives_byte_identical_files(tmp_path):
    t = synthetic_pulses(200, seed=5, n_samples=(100, 256))

    def digest(p):
        return hashlib.sha256(p.read_bytes()).hexdigest()

    for storage in ("internal", "external"):
        a = write_waveform_las(tmp_path / f"a_{storage}.las", t, storage=storage)
        b = write_waveform_las(tmp_path / f"b_{storage}.las", t, storage=storage)
        assert digest(a) == digest(b)
        if storage == "external":
            assert digest(a.with_suffix(".wdp")) == digest(b.with_suffix(".wdp"))


def test_streaming_writer_equals_one_shot(tmp_path):
    t = synthetic_pulses(1000, seed=6, n_samples=(64, 128))
    one = write_waveform_las(tmp_path / "one.las", t, offsets=(500_000.0, 6_800_000.0, 0.0))
    with WaveformLasWriter(tmp_path / "many.las", offsets=(500_000.0, 6_800_000.0, 0.0)) as w:
        for start in range(0, 1000, 137):
            w.write(t.slice(start, 137))
    assert one.read_bytes() == (tmp_path / "many.las").read_bytes()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left


def test_agc_in_extra_bytes_dimension(tmp_path):
    t = synthetic_pulses(100, seed=7)
    agc = np.linspace(0.5, 1000.25, 100)  # not 8-bit: needs a float extra-bytes dimension
    t = t.set_column(t.schema.get_field_index("agc"), "agc", pa.array(agc))
    path = write_waveform_las(tmp_path / "x.las", t, agc_attribute="AGC gain")
    las = laspy.read(path)
    assert "AGC gain" in las.point_format.extra_dimension_names
    back = read_waveform_las(path, agc_attribute="AGC gain")
    np.testing.assert_array_equal(back["agc"].to_numpy(), agc)
    assert_round_trip(t, back)
    back = read_waveform_las(path, agc_attribute="agc gain")  # case-insensitive fallback
    np.testing.assert_array_equal(back["agc"].to_numpy(), agc)


def test_multi_bucket_reading_equals_in_memory(tmp_path):
    """The bounded-memory path (GPS-time buckets spilled to disk) gives the same table."""
    t = synthetic_pulses(3000, seed=8, max_echoes=3)
    path = write_waveform_las(tmp_path / "m.las", t, storage="external")
    whole = read_waveform_las(path)
    spill = tmp_path / "spill"
    spill.mkdir()
    reader = WaveformPulseReader(path, chunk_points=700, bucket_points=1000, batch_pulses=333, tmp_dir=spill)
    parts = list(reader)
    # points in time order (as the writer puts them): buckets cut in memory, none spilled
    assert reader.n_passes == 2 and reader.stats.n_buckets >= 5 and not reader.stats.spilled
    assert_tables_equal(pa.concat_tables(parts), whole)
    assert list(spill.iterdir()) == []
    assert_round_trip(t, whole)


def test_ordered_buckets_keep_the_returns_of_a_pulse_together(tmp_path):
    """Bucket cuts fall between GPS times, even when a cut lands inside a pulse's returns
    (every pulse has 3 returns, 250-point buckets of 101-point chunks)."""
    t = synthetic_pulses(900, seed=12, max_echoes=3)
    t = t.filter(pc.equal(t["n_echoes"], 3))
    path = write_waveform_las(tmp_path / "o.las", t)
    reader = WaveformPulseReader(path, chunk_points=101, bucket_points=250, batch_pulses=97)
    back = pa.concat_tables(list(reader))
    assert not reader.stats.spilled and reader.stats.n_buckets >= 2
    assert reader.stats.n_split_pulses == 0
    assert_tables_equal(back, read_waveform_las(path))
    assert_round_trip(t, back)
    # buckets smaller than a pulse: each grows until its GPS time changes
    few = write_waveform_las(tmp_path / "few.las", t.slice(0, 12))
    reader = WaveformPulseReader(few, chunk_points=1, bucket_points=2)
    assert_tables_equal(pa.concat_tables(list(reader)), read_waveform_las(few))
    assert reader.stats.n_buckets == 12 and not reader.stats.spilled


def test_writer_rejects_what_las_cannot_hold(tmp_path):
    from waveforest.io.las.format import LasWaveformError

    t = synthetic_pulses(20, seed=9)
    bad = t.set_column(t.schema.get_field_index("samples"), "samples", pa.array([[0.5, 1.0]] * 20, pa.list_(pa.float32())))
    with pytest.raises(LasWaveformError, match="whole number"):
        write_waveform_las(tmp_path / "s.las", bad)
    shifted = t.set_column(t.schema.get_field_index("anchor_z"), "anchor_z", pa.array(t["anchor_z"].to_numpy() + 0.5))
    with pytest.raises(LasWaveformError, match="anchor"):
        write_waveform_las(tmp_path / "g.las", shifted)
    dup = pa.concat_tables([t.slice(0, 1), t.slice(0, 1)])
    with pytest.raises(LasWaveformError, match="gps_time"):
        write_waveform_las(tmp_path / "d.las", dup)
    with pytest.raises(LasWaveformError, match=r"\[0, 255\]"):
        write_waveform_las(tmp_path / "b.las", synthetic_pulses(5, bits=16), bits=8)
    late = t.set_column(t.schema.get_field_index("gps_time"), "gps_time", pa.array(t["gps_time"].to_numpy() + 7e5))
    with pytest.raises(LasWaveformError, match="GPS week time"):
        write_waveform_las(tmp_path / "w.las", late)
    assert list(tmp_path.iterdir()) == []  # nothing left behind by the failures


def test_adjusted_standard_gps_time_is_declared(tmp_path):
    """gps_time_type 'standard': global encoding bit 0 set (LAS 1.4 R15: adjusted standard GPS
    time), the times written as given; 'week' (default) leaves it clear."""
    t = synthetic_pulses(20, seed=9)
    late = t.set_column(t.schema.get_field_index("gps_time"), "gps_time", pa.array(t["gps_time"].to_numpy() + 3e8))
    std = laspy.read(write_waveform_las(tmp_path / "std.las", late, gps_time_type="standard"))
    week = laspy.read(write_waveform_las(tmp_path / "week.las", t))
    assert int(std.header.global_encoding.value) & 1 and not int(week.header.global_encoding.value) & 1
    assert np.allclose(np.unique(std.gps_time), np.sort(late["gps_time"].to_numpy()))


TM35FIN = ('PROJCS["ETRS89 / TM35FIN(E,N)",GEOGCS["ETRS89",DATUM["European_Terrestrial_Reference_System_1989",'
           'SPHEROID["GRS 1980",6378137,298.257222101]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],'
           'AUTHORITY["EPSG","4258"]],PROJECTION["Transverse_Mercator"],UNIT["metre",1],AUTHORITY["EPSG","3067"]]')


@pytest.mark.parametrize("wkt, model, key, code", [
    (TM35FIN, 1, 3072, 3067),  # projected: its top-level EPSG code, not the datum's 4258
    ('GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",6378137,298.257223563]],AUTHORITY["EPSG","4326"]]',
     2, 2048, 4326),
    ('LOCAL_CS["scene frame",LOCAL_DATUM["scene",0],UNIT["metre",1]]', 32767, None, None),
])
def test_las13_carries_geotiff_keys_beside_the_wkt(tmp_path, wkt, model, key, code):
    """LAS 1.3 knows GeoTIFF keys only: the directory (34735) laspy parses, with the WKT's EPSG
    code or a user-defined model cited by name; LAS 1.4 keeps the WKT alone (global encoding bit 4)."""
    t = synthetic_pulses(10, seed=4)
    las = laspy.read(write_waveform_las(tmp_path / "c13.las", t, version="1.3", point_format=4, wkt=wkt))
    keys = {k.id: k.value_offset for k in las.header.vlrs.get("GeoKeyDirectoryVlr")[0].geo_keys}
    assert keys[1024] == model and (key is None or keys[key] == code)
    assert any(v.record_id == 2112 for v in las.header.vlrs)
    if key is None:  # the citation key points into GeoAsciiParams
        assert las.header.vlrs.get("GeoAsciiParamsVlr")[0].strings[0] == "scene frame|"
    las14 = laspy.read(write_waveform_las(tmp_path / "c14.las", t, wkt=wkt))
    assert not las14.header.vlrs.get("GeoKeyDirectoryVlr") and int(las14.header.global_encoding.value) & 16


def test_creation_date_is_today_or_source_date_epoch(monkeypatch):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1388707200")  # 2014-01-03 00:00 UTC
    assert creation_today() == (3, 2014)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    with pytest.raises(WaveforestError, match="SOURCE_DATE_EPOCH='yesterday': expected whole seconds"):
        creation_today()
    monkeypatch.delenv("SOURCE_DATE_EPOCH")
    day, year = creation_today()
    assert year >= 2025 and 1 <= day <= 366
