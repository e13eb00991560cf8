"""LAZ in: the point records LAZ-compressed (laspy + lazrs), the waveforms in a ``.wdp`` beside
the file or inside it after the compressed points. The pulse tables must be sample-exact
against the same file as LAS (the truth is the LAS reading, itself checked against the
independent byte reader of ``tests/reference_io.py`` elsewhere).
"""

import shutil
import struct

import laspy
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from fixtures.pulses import synthetic_pulses
from reference_io import RIEGL, patch

from waveforest.cli import main
from waveforest.io.las import open_waveform_las, read_waveform_las, summarise
from waveforest.io.las.format import LasWaveformError
from waveforest.io.las.write import write_waveform_las

START_OF_WAVEFORM_DATA = 227
"""Byte of the header field "start of waveform data packet record" (uint64, LAS 1.3 and 1.4)."""


def assert_tables_identical(a: pa.Table, b: pa.Table) -> None:
    """Same columns, types and values; NaN equals NaN; list columns offset by offset."""
    assert a.schema == b.schema
    assert a.num_rows == b.num_rows
    for name in a.column_names:
        ca, cb = a.column(name).combine_chunks(), b.column(name).combine_chunks()
        if pa.types.is_list(ca.type):
            np.testing.assert_array_equal(ca.offsets.to_numpy(), cb.offsets.to_numpy(), err_msg=name)
            ca, cb = ca.flatten(), cb.flatten()
        va, vb = ca.to_numpy(zero_copy_only=False), cb.to_numpy(zero_copy_only=False)
        if va.dtype.kind == "f":
            assert np.array_equal(va, vb, equal_nan=True), name
        else:
            assert np.array_equal(va, vb), name


def laz_copy(las_path, laz_path, waveforms: str = "external"):
    """A LAZ copy of a LAS waveform file, written with laspy + lazrs.

    ``external``: the ``.wdp`` copied beside it. ``internal``: the file's waveform record
    appended after the compressed points and the header's start_of_waveform_data set to it
    (as a LASzip writer that keeps internal waveforms lays them out).
    """
    las = laspy.read(las_path)
    las.evlrs = []  # an internal LAS 1.4 record is an EVLR; appended by hand below instead
    las.write(laz_path, laz_backend=laspy.LazBackend.Lazrs)
    if waveforms == "external":
        shutil.copy(las_path.with_suffix(".wdp"), laz_path.with_suffix(".wdp"))
        return laz_path
    wf = open_waveform_las(las_path).waveform
    with open(las_path, "rb") as fh:
        fh.seek(wf.base)
        record = fh.read(wf.size)
    start = laz_path.stat().st_size
    with open(laz_path, "ab") as fh:
        fh.write(record)
    patch(laz_path, START_OF_WAVEFORM_DATA, "<Q", start)
    return laz_path


@pytest.fixture(scope="module")
def riegl(tmp_path_factory):
    folder = tmp_path_factory.mktemp("riegl")
    las = folder / "riegl_fwf.las"
    shutil.copy(RIEGL, las)
    shutil.copy(RIEGL.with_suffix(".wdp"), las.with_suffix(".wdp"))
    (folder / "laz").mkdir()
    return las, laz_copy(las, folder / "laz" / "riegl_fwf.laz")


def test_real_riegl_laz_is_sample_exact(riegl):
    las, laz = riegl
    f = open_waveform_las(laz)
    assert f.compressed and f.point_format == 9 and f.waveform.storage == "external"
    assert laz.stat().st_size < 0.5 * las.stat().st_size  # really compressed
    with pytest.warns(Warning, match="no AGC"):
        a = read_waveform_las(las)
    with pytest.warns(Warning, match="no AGC"):
        b = read_waveform_las(laz)
    assert a.num_rows == 2368
    assert_tables_identical(a, b)


def test_laz_streams_in_buckets_as_las(riegl):
    """Small chunks and buckets (the two-pass, spilled path of large files) give the same table."""
    las, laz = riegl
    kw = dict(chunk_points=97, bucket_points=300, batch_pulses=128, agc_attribute=None)
    a = read_waveform_las(las, **kw)
    b = read_waveform_las(laz, **kw)
    assert_tables_identical(a, b)


def test_laz_through_ingest_cli(riegl, tmp_path):
    las, laz = riegl
    outs = []
    for src in (las, laz):
        out = tmp_path / f"{src.suffix[1:]}.parquet"
        main(["ingest", str(src), "--out", str(out), "--no-progress", "--dataset", "riegl"])
        outs.append(pq.read_table(out))
    assert_tables_identical(*outs)


def test_laz_summary(riegl):
    las, laz = riegl
    a, b = summarise(las), summarise(laz)
    assert (a.n_points, a.n_pulses, a.n_packets) == (b.n_points, b.n_pulses, b.n_packets) == (2535, 2368, 2375)


@pytest.mark.parametrize("version", ["1.3", "1.4"])
def test_laz_with_internal_waveforms(tmp_path, version):
    table = synthetic_pulses(80, seed=29, n_samples=(64, 128))
    las = write_waveform_las(tmp_path / f"in{version}.las", table, version=version, bits=8, storage="internal")
    laz = laz_copy(las, tmp_path / f"in{version}.laz", waveforms="internal")
    f = open_waveform_las(laz)
    assert f.compressed and f.waveform.storage == "internal" and f.waveform.header_ok
    a = read_waveform_las(las, agc_attribute=None)
    b = read_waveform_las(laz, agc_attribute=None, dataset=las.stem)
    assert_tables_identical(a, b)
    np.testing.assert_array_equal(b.column("samples").combine_chunks().flatten().to_numpy(),
                                  table.column("samples").combine_chunks().flatten().to_numpy())


def test_laz_internal_waveforms_without_a_record_is_a_clear_error(tmp_path):
    """A LAZ that says 'internal' but whose waveform record is not where the header points
    (a writer that dropped it) is refused, not decoded from compressed bytes."""
    table = synthetic_pulses(20, seed=3, n_samples=(64, 64))
    las = write_waveform_las(tmp_path / "in.las", table, version="1.3", bits=8, storage="internal")
    laz = laz_copy(las, tmp_path / "in.laz", waveforms="internal")
    start = struct.unpack("<Q", laz.read_bytes()[START_OF_WAVEFORM_DATA:START_OF_WAVEFORM_DATA + 8])[0]
    patch(laz, START_OF_WAVEFORM_DATA, "<Q", start - 100)  # a stale pointer into the compressed points
    with pytest.raises(LasWaveformError, match="overlaps the point records"):
        open_waveform_las(laz)
    patch(laz, START_OF_WAVEFORM_DATA, "<Q", start + 10)  # no record header there
    with pytest.raises(LasWaveformError, match="must follow the compressed points.*wdp"):
        open_waveform_las(laz)
    patch(laz, START_OF_WAVEFORM_DATA, "<Q", 0)
    with pytest.raises(LasWaveformError, match="no waveform data packet record"):
        open_waveform_las(laz)


def test_laz_without_laszip_vlr_is_a_clear_error(tmp_path):
    table = synthetic_pulses(20, seed=3, n_samples=(64, 64))
    las = write_waveform_las(tmp_path / "in.las", table, version="1.4", storage="external")
    patch(las, 104, "<B", 9 | 0x80)
    with pytest.raises(LasWaveformError, match="LAZ-compressed.*no LASzip VLR"):
        open_waveform_las(las)
