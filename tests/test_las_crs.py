"""The coordinate system of a LAS file, from a VLR or (LAS 1.4) an EVLR, as ``info`` and
``quicklook`` name it."""

import struct

from fixtures.pulses import synthetic_pulses

from waveforest.io.las import summarise, write_waveform_las

WKT = 'PROJCS["ETRS89 / TM35FIN(E,N)",GEOGCS["ETRS89"],AUTHORITY["EPSG","3067"]]'


def _append_evlr(path, user_id: bytes, record_id: int, body: bytes) -> None:
    """Append one EVLR to a LAS 1.4 file without EVLRs and point the header at it."""
    with open(path, "r+b") as fh:
        fh.seek(0, 2)
        start = fh.tell()
        fh.write(struct.pack("<H16sHQ32s", 0, user_id, record_id, len(body), b"test") + body)
        fh.seek(235)  # LAS 1.4 header: start of first EVLR (u64), number of EVLRs (u32)
        fh.write(struct.pack("<QI", start, 1))


def test_crs_in_a_wkt_vlr(tmp_path):
    las = write_waveform_las(tmp_path / "v.las", synthetic_pulses(20, seed=5), storage="external", wkt=WKT)
    assert summarise(las).crs == "ETRS89 / TM35FIN(E,N) (EPSG:3067; WKT VLR)"


def test_crs_in_a_wkt_evlr(tmp_path):
    las = write_waveform_las(tmp_path / "e.las", synthetic_pulses(20, seed=5), storage="external")
    assert summarise(las).crs == "not stated"
    _append_evlr(las, b"LASF_Projection", 2112, WKT.encode("ascii") + b"\0")
    assert summarise(las).crs == "ETRS89 / TM35FIN(E,N) (EPSG:3067; WKT EVLR)"


def test_crs_in_geotiff_key_evlrs(tmp_path):
    las = write_waveform_las(tmp_path / "g.las", synthetic_pulses(20, seed=5), storage="external")
    # GeoKeyDirectory: header (1, 1, 0, 1 key) and ProjectedCSTypeGeoKey (3072) = 3067
    keys = struct.pack("<8H", 1, 1, 0, 1, 3072, 0, 1, 3067)
    _append_evlr(las, b"LASF_Projection", 34735, keys)
    assert summarise(las).crs == "user-defined (EPSG:3067; GeoTIFF keys, EVLR)"


def test_a_garbled_crs_evlr_reads_as_not_stated(tmp_path):
    las = write_waveform_las(tmp_path / "b.las", synthetic_pulses(20, seed=5), storage="external")
    _append_evlr(las, b"LASF_Projection", 34735, b"\x01")
    assert summarise(las).crs == "not stated"
