"""Real-world files are messy: what the LAS spec allows and real writers produce still reads.

Each test takes a file of known content (written from a synthetic table), makes it messy
the way real writers do, and checks that the pulse table is the one of the clean file.
"""

import shutil
import struct

import laspy
import numpy as np
import pyarrow as pa
import pytest
from fixtures.pulses import synthetic_pulses
from laspy.vlrs.known import WaveformPacketStruct, WaveformPacketVlr
from reference_io import patch, point_field_position, reference_header, vlr_body_position
from test_io_las_roundtrip import assert_round_trip, assert_tables_equal

from waveforest.constants import RANGE_PER_NS
from waveforest.io.las.format import LasWaveformWarning
from waveforest.io.las.info import format_summary, summarise
from waveforest.io.las.read import WaveformPulseReader, read_waveform_las
from waveforest.io.las.write import write_waveform_las

SPLIT_AT_NS = 30.0
"""Where the split-packet test cuts a waveform in two, ns from its first sample."""
SPLIT_WINDOW = 120
"""Samples of the second packet (a layout the file already describes)."""
SPLIT_TIME_TOL_NS = 0.02
"""Echo time through the geometry: 1 mm quantisation of two points ~ 0.012 ns."""


@pytest.fixture
def clean(tmp_path):
    t = synthetic_pulses(400, seed=21, bits=16, n_samples=(120, 256), max_echoes=3)
    path = write_waveform_las(tmp_path / "clean.las", t, bits=16, storage="external")
    return t, path


def _copy(path, name):
    dst = path.with_name(name)
    shutil.copy(path, dst)
    if path.with_suffix(".wdp").exists():
        shutil.copy(path.with_suffix(".wdp"), dst.with_suffix(".wdp"))
    return dst


def test_header_bounds_and_counts_of_a_whole_flight_line(clean):
    t, path = clean
    messy = _copy(path, "line.las")
    # bounds of the whole flight line, return counts of the whole line (larger than the file)
    patch(messy, 179, "<6d", 600_000.0, 400_000.0, 6_900_000.0, 6_700_000.0, 900.0, -50.0)
    patch(messy, 255, "<15Q", *([10**7] * 15))
    patch(messy, 111, "<5I", *([10**7] * 5))
    back = read_waveform_las(messy)
    assert_tables_equal(back.drop_columns(["dataset"]), read_waveform_las(path).drop_columns(["dataset"]))
    assert_round_trip(t, back)
    text = format_summary(summarise(messy))
    assert "differ from the points" in text and "600000.000" in text


def test_legacy_point_count_only(clean):
    """LAS 1.4 with a legacy format (4) whose writer filled only the 32-bit count."""
    t, _ = clean
    path = write_waveform_las(clean[1].with_name("legacy.las"), t, bits=16, point_format=4)
    n = reference_header(path)["n_points"]
    patch(path, 247, "<Q", 0)  # 64-bit count 0, legacy count kept
    assert struct.unpack("<I", path.read_bytes()[107:111])[0] == n
    assert_round_trip(t, read_waveform_las(path))


def test_malformed_wdp_header_warns_and_trusts_offsets(clean):
    t, path = clean
    messy = _copy(path, "badwdp.las")
    wdp = messy.with_suffix(".wdp")
    patch(wdp, 0, "<60s", b"\x00garbage written by some writer" + b"\xff" * 29)
    with pytest.warns(LasWaveformWarning, match="malformed"):
        back = read_waveform_las(messy)
    assert_round_trip(t, back)
    # a record length off by the header size (another common writer slip)
    patch(wdp, 0, "<H16sHQ32s", 0, b"LASF_Spec", 65535, wdp.stat().st_size, b"")
    with pytest.warns(LasWaveformWarning, match="its record header announces"):
        assert_round_trip(t, read_waveform_las(messy))


def test_unused_descriptors_with_zero_samples(clean):
    """Unused, empty descriptors (as RIEGL writes 98 of them), added by another writer (laspy)."""
    t, path = clean
    las = laspy.read(path)
    for rid in (110, 150, 354):
        v = WaveformPacketVlr(rid, description="unused")
        v.parsed_record = WaveformPacketStruct()  # 0 bits, 0 samples, 0 ps
        las.header.vlrs.append(v)
    messy = path.with_name("unused.las")
    las.write(messy)
    shutil.copy(path.with_suffix(".wdp"), messy.with_suffix(".wdp"))
    back = read_waveform_las(messy)
    assert_round_trip(t, back)
    s = summarise(messy)
    assert len(s.las.descriptors) == 5 and sum(d.empty for d in s.las.descriptors.values()) == 3
    assert "3 unused (3 of them empty" in format_summary(s)


def test_points_in_any_order(clean):
    t, path = clean
    messy = _copy(path, "shuffled.las")
    h = reference_header(messy)
    raw = bytearray(messy.read_bytes())
    start, rl, n = h["offset_to_points"], h["record_length"], h["n_points"]
    records = np.frombuffer(bytes(raw[start : start + n * rl]), np.uint8).reshape(n, rl)
    perm = np.random.default_rng(0).permutation(n)
    raw[start : start + n * rl] = records[perm].tobytes()
    messy.write_bytes(bytes(raw))
    back = read_waveform_las(messy)
    assert_round_trip(t, back)
    # and through the bounded-memory (bucketed) path
    folder = messy.parent / "spill"
    folder.mkdir()
    reader = WaveformPulseReader(messy, chunk_points=97, bucket_points=150, batch_pulses=50, tmp_dir=folder)
    spill = pa.concat_tables(list(reader))
    assert reader.stats.spilled  # out of time order: the buckets go through disk
    assert list(folder.iterdir()) == []  # and their files are removed
    assert_tables_equal(spill, back)


def test_returns_of_one_pulse_in_two_packets(clean):
    """As some writers do for long records: the later returns get a packet of their own.

    For pulses with >= 2 echoes a window of the waveform from SPLIT_AT_NS is appended to
    the .wdp as a new packet, and the returns after SPLIT_AT_NS point at it with
    their location relative to its first sample. The pulse table must not change.
    """
    t, path = clean
    messy = _copy(path, "split.las")
    wdp = messy.with_suffix(".wdp")
    n_echo = t["n_echoes"].to_numpy()
    times = t["echo_time_ns"].to_pylist()
    samples = t["samples"].to_pylist()
    sampling = t["sampling_ns"].to_numpy()
    descs = {ns: i for i, ns in ((i, struct.unpack("<BBII", messy.read_bytes()[vlr_body_position(messy, 99 + i) :][:10])[2]) for i in (1, 2))}
    first_point = np.concatenate([[0], np.cumsum(n_echo)[:-1]])
    n_split = 0
    with open(wdp, "ab") as fh:
        for p in np.flatnonzero(n_echo >= 2)[:40]:
            later = [k for k in range(n_echo[p]) if times[p][k] > SPLIT_AT_NS]
            if not later or later[0] == 0:
                continue
            cut = int(SPLIT_AT_NS / sampling[p])
            if len(samples[p]) < cut + SPLIT_WINDOW:
                continue
            tail = np.asarray(samples[p][cut : cut + SPLIT_WINDOW], dtype="<u2")  # a 120-sample window
            offset = fh.tell()
            fh.write(tail.tobytes())
            for k in later:
                i = first_point[p] + k
                patch(messy, point_field_position(messy, i, "wpi"), "<BQI", descs[len(tail)], offset, tail.nbytes)
                patch(messy, point_field_position(messy, i, "loc"), "<f", (times[p][k] - cut * sampling[p]) * 1000.0)
            n_split += 1
    patch(wdp, 0, "<H16sHQ", 0, b"LASF_Spec", 65535, wdp.stat().st_size - 60)
    assert n_split >= 5
    reader = WaveformPulseReader(messy)
    back = pa.concat_tables(list(reader))
    assert reader.stats.n_split_pulses == n_split
    np.testing.assert_allclose(
        np.concatenate(back["echo_time_ns"].to_pylist()), np.concatenate(times), rtol=0, atol=SPLIT_TIME_TOL_NS
    )
    assert back["samples"].to_pylist() == samples  # the packet of the first return
    assert back["n_echoes"].to_pylist() == n_echo.tolist()
    s = summarise(messy)
    assert (s.n_pulses, s.n_packets, s.n_split_pulses) == (t.num_rows, t.num_rows + n_split, n_split)


def test_file_without_agc(tmp_path):
    t = synthetic_pulses(50, seed=22)
    path = write_waveform_las(tmp_path / "noagc.las", t, agc_attribute=None)
    with pytest.warns(LasWaveformWarning, match="0 for every point"):
        back = read_waveform_las(path)
    assert np.all(np.isnan(back["agc"].to_numpy()))
    assert_round_trip(t, back, agc_exact=False)
    with pytest.warns(LasWaveformWarning, match="no point attribute 'AGC'"):
        back = read_waveform_las(path, agc_attribute="AGC")
    assert np.all(np.isnan(back["agc"].to_numpy()))
    # bucketed path decides the same before writing any row
    with pytest.warns(LasWaveformWarning, match="0 for every point"):
        spill = read_waveform_las(path, bucket_points=40, chunk_points=30)
    assert np.all(np.isnan(spill["agc"].to_numpy()))


def test_pulses_without_waveform_are_skipped(tmp_path):
    t = synthetic_pulses(30, seed=23)
    empty = [[] if i % 5 == 0 else s for i, s in enumerate(t["samples"].to_pylist())]
    t2 = t.set_column(t.schema.get_field_index("samples"), "samples", pa.array(empty, pa.list_(pa.float32())))
    path = write_waveform_las(tmp_path / "nowf.las", t2)
    with pytest.warns(LasWaveformWarning, match="6 pulse"):
        back = read_waveform_las(path)
    keep = np.arange(30) % 5 != 0
    assert back["pulse_id"].to_pylist() == np.flatnonzero(keep).tolist()  # ids stay those of GPS order
    assert_round_trip(t.filter(pa.array(keep)), back)


def test_global_encoding_without_waveform_bits(clean, tmp_path):
    t, path = clean
    for storage in ("external", "internal"):
        p = write_waveform_las(tmp_path / f"ge_{storage}.las", t, bits=16, storage=storage)
        patch(p, 6, "<H", 0)
        with pytest.warns(LasWaveformWarning, match="neither waveform bit"):
            assert_round_trip(t, read_waveform_las(p))


def test_larger_packet_size_than_descriptor_warns(clean):
    t, path = clean
    messy = _copy(path, "bigsize.las")
    size = struct.unpack("<I", messy.read_bytes()[point_field_position(messy, 0, "size") :][:4])[0]
    patch(messy, point_field_position(messy, 0, "size"), "<I", size + 2)
    with pytest.warns(LasWaveformWarning, match="exceeds descriptor"):
        assert_round_trip(t, read_waveform_las(messy))


def test_geometry_of_split_relation_is_consistent():
    """The split test relies on this: moving the packet start moves L by the same time."""
    anchor, d, t = np.array([0.0, 0.0, 100.0]), np.array([0.0, 0.6, -0.8]), 42.0
    p = anchor + d * t * RANGE_PER_NS
    new_anchor = anchor + d * SPLIT_AT_NS * RANGE_PER_NS
    np.testing.assert_allclose(new_anchor + d * (t - SPLIT_AT_NS) * RANGE_PER_NS, p)
