"""Open and check a LAS 1.3/1.4 waveform file: header, descriptors, waveform data location.

:func:`open_waveform_las` reads the public header block and walks the VLR and EVLR headers
itself (numpy, so that the legacy and 64-bit point counts and the waveform fields are seen
as written, and every count and length is bounded by the file's geometry before anything
is read), then hands laspy the checked header and VLR bytes for the point format and its
extra-bytes dimensions. EVLR bodies are not read (the waveform record may be gigabytes).
It returns a :class:`LasWaveformFile`, or raises :class:`waveforest.io.las.format.LasWaveformError`
naming the file, the field and what was expected.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from waveforest.io.las.format import (
    EVLR_HEADER,
    EXTRA_BYTES_DESCRIPTOR,
    EXTRA_BYTES_RECORD_ID,
    GE_WAVEFORM_EXTERNAL,
    GE_WAVEFORM_INTERNAL,
    HEADER_13,
    HEADER_14,
    HEADER_SIZE,
    LAS_SIGNATURE,
    LASF_PROJECTION,
    LASF_SPEC,
    LASZIP_RECORD_ID,
    LASZIP_USER_ID,
    MAX_PROJECTION_BYTES,
    VLR_HEADER,
    WAVEFORM_HEADER_SIZE,
    WAVEFORM_POINT_FORMATS,
    WAVEFORM_RECORD_ID,
    WPD_BODY,
    WPD_FIRST_RECORD_ID,
    WPD_INDEX_OFFSET,
    WPD_LAST_RECORD_ID,
    LasWaveformError,
    LasWaveformWarning,
    WavePacketDescriptor,
    decode_text,
    point_dtype,
    warn,
)


@dataclass(frozen=True)
class WaveformData:
    """Where the waveform packets of a file are.

    Attributes
    ----------
    path : Path
        The file holding the packets (the LAS file itself or its ``.wdp``).
    base : int
        Absolute position in ``path`` that the points' byte offsets count from (the start
        of the 60-byte Waveform Data Packet Record header).
    size : int
        Bytes available from ``base`` to the end of ``path``.
    storage : str
        ``internal`` or ``external``.
    header_ok : bool
        Whether the 60-byte record header at ``base`` is well formed.
    record_length : int
        Byte count that header declares (0 if malformed).
    """

    path: Path
    base: int
    size: int
    storage: str
    header_ok: bool
    record_length: int


@dataclass(frozen=True)
class LasWaveformFile:
    """A checked LAS waveform file: header facts, descriptors and waveform data location."""

    path: Path
    file_size: int
    version: str
    point_format: int
    record_length: int
    n_points: int
    offset_to_point_data: int
    global_encoding: int
    scales: np.ndarray
    offsets: np.ndarray
    header_mins: np.ndarray
    header_maxs: np.ndarray
    header_points_by_return: np.ndarray
    system_identifier: str
    generating_software: str
    creation: tuple[int, int]
    descriptors: dict[int, WavePacketDescriptor]
    waveform: WaveformData
    dimension_names: tuple[str, ...]
    extra_dimension_names: tuple[str, ...]
    header_bytes: bytes | None = None
    """The header and VLR bytes laspy reads in place of the file's (text fields patched), or None."""
    compressed: bool = False
    """The point records are LAZ-compressed (LASzip; decompressed by laspy's lazrs backend)."""
    projection_evlrs: tuple[tuple[int, bytes], ...] = ()
    """(record id, body) of each LASF_Projection EVLR (a LAS 1.4 CRS may live there)."""

    def descriptor_tables(self) -> dict[str, np.ndarray]:
        """Per descriptor index (0..255) lookup arrays: n_samples, sample_bytes, spacing_ps, gain, offset."""
        lut = {
            "n_samples": np.zeros(256, np.int64),
            "sample_bytes": np.zeros(256, np.int64),
            "spacing_ps": np.zeros(256, np.float64),
            "gain": np.full(256, np.nan),
            "offset": np.full(256, np.nan),
        }
        for i, d in self.descriptors.items():
            lut["n_samples"][i] = d.n_samples
            lut["sample_bytes"][i] = d.bytes_per_sample or 0
            lut["spacing_ps"][i] = d.spacing_ps
            lut["gain"][i] = d.gain
            lut["offset"][i] = d.offset
        return lut


def fail(path: Path, message: str) -> LasWaveformError:
    """The error for ``path``: one message naming the file and the problem."""
    return LasWaveformError(f"{path}: {message}")


def _read_at(path: Path, pos: int, n: int) -> bytes:
    with open(path, "rb") as fh:
        fh.seek(pos)
        return fh.read(n)


def _record_header(path: Path, pos: int, file_size: int) -> np.void | None:
    if pos + EVLR_HEADER.itemsize > file_size:
        return None
    return np.frombuffer(_read_at(path, pos, EVLR_HEADER.itemsize), EVLR_HEADER)[0]


def _is_waveform_record(h: np.void | None) -> bool:
    """The record header names the waveform data packet record (LASF_Spec / 65535)."""
    return h is not None and bytes(h["user_id"]).rstrip(b"\0") == LASF_SPEC and int(h["record_id"]) == WAVEFORM_RECORD_ID


def _is_waveform_header(h: np.void | None, available: int) -> bool:
    """:func:`_is_waveform_record`, of a length that fits in ``available`` bytes with its header."""
    return _is_waveform_record(h) and int(h["record_length"]) <= available - WAVEFORM_HEADER_SIZE


def find_wdp(path: Path) -> Path | None:
    """The ``.wdp`` file beside a LAS file (same stem), if there is one."""
    for suffix in (".wdp", ".WDP", ".Wdp"):
        cand = path.with_suffix(suffix)
        if cand.is_file():
            return cand
    return None


def open_waveform_las(path: str | os.PathLike) -> LasWaveformFile:
    """Check a LAS waveform file and describe it; raise :class:`LasWaveformError` if unusable.

    Checked here, before laspy sees a byte: LAS signature and version (1.3 or 1.4), a
    waveform point format (4, 5, 9, 10) (LAZ-compressed points need a LASzip VLR and a LAZ
    backend; see :func:`_laz_end_of_points`), finite non-zero scale factors
    and finite offsets, the header size, the VLR count and every VLR's length against the
    header geometry (each VLR header is 54 bytes and all lie between the end of the header
    and ``offset_to_point_data``), the EVLR start and count against the file size (each
    EVLR header is 60 bytes), the point records all present (header count x record length
    fits in the file), no point records hidden behind a header count of 0, and the waveform
    data present (external ``.wdp`` or internal record, as the global encoding says). Text
    fields that are not UTF-8 (VLR user ids and descriptions, extra-bytes names) are read
    on with '?' in place of the bad bytes and a
    :class:`waveforest.io.las.format.LasWaveformWarning`.
    Per-point checks (descriptor index, packet bounds) happen while reading points. Header
    bounds and return counts are not checked: real files often carry those of a whole
    flight line.
    """
    path = Path(path)
    if not path.is_file():
        raise fail(path, "no such file")
    file_size = path.stat().st_size
    hdr, version = _read_header(path)
    point_format, record_length, core_length, compressed = _point_layout(path, hdr)
    scales, offsets = _scales_offsets(path, hdr)
    offset_to_points = int(hdr["offset_to_point_data"])
    prefix, vlrs = _read_vlrs(path, hdr, version, file_size)
    if compressed:
        _check_laz(path, vlrs)
    prefix, fixed = _utf8_text_fields(prefix, vlrs)
    if fixed:
        warn(f"{path}: non-UTF-8 bytes in {', '.join(fixed)} replaced by '?'; reading on")
    _check_extra_bytes(path, prefix, vlrs, point_format, record_length - core_length)

    n_points = int(hdr["legacy_point_count"])
    by_return = np.asarray(hdr["legacy_points_by_return"], dtype=np.int64)
    if version == "1.4":
        n_points = int(hdr["point_count"]) or n_points
        by_return = np.asarray(hdr["points_by_return"], dtype=np.int64)
    dim_names, extra_names = _laspy_dimensions(path, prefix, point_format, record_length)

    if compressed:
        end_of_points = _laz_end_of_points(path, offset_to_points, file_size)
    else:
        end_of_points = offset_to_points + n_points * record_length
    if not compressed and end_of_points > file_size:
        have = (file_size - offset_to_points) // record_length
        raise fail(
            path,
            f"truncated file: the header announces {n_points} points of {record_length} bytes from byte "
            f"{offset_to_points}, but the file has {file_size} bytes (room for {have} points)",
        )
    evlrs = _evlr_headers(path, hdr, file_size, end_of_points) if version == "1.4" else []
    if not compressed:  # LAZ: the compressed size says nothing about the count; the reader checks it
        _check_point_count(path, hdr, n_points, record_length, file_size, evlrs)
    descriptors, evlr_waveform = _descriptors(path, prefix, vlrs, evlrs)
    projection = tuple((int(h["record_id"]), _read_at(path, pos + EVLR_HEADER.itemsize, int(h["record_length"])))
                       for pos, h in evlrs if bytes(h["user_id"]).rstrip(b"\0") == LASF_PROJECTION
                       and int(h["record_length"]) <= MAX_PROJECTION_BYTES)

    waveform = _locate_waveform_data(path, file_size, int(hdr["global_encoding"]), int(hdr["start_of_waveform_data"]),
                                     evlr_waveform, end_of_points, compressed)
    return LasWaveformFile(
        path=path,
        file_size=file_size,
        version=version,
        point_format=point_format,
        record_length=record_length,
        n_points=n_points,
        offset_to_point_data=offset_to_points,
        global_encoding=int(hdr["global_encoding"]),
        scales=scales,
        offsets=offsets,
        header_mins=np.array([hdr["min_x"], hdr["min_y"], hdr["min_z"]], dtype=np.float64),
        header_maxs=np.array([hdr["max_x"], hdr["max_y"], hdr["max_z"]], dtype=np.float64),
        header_points_by_return=by_return.copy(),
        system_identifier=decode_text(hdr["system_identifier"]),
        generating_software=decode_text(hdr["generating_software"]),
        creation=(int(hdr["creation_day"]), int(hdr["creation_year"])),
        descriptors=dict(sorted(descriptors.items())),
        waveform=waveform,
        dimension_names=dim_names,
        extra_dimension_names=extra_names,
        header_bytes=prefix if fixed else None,
        compressed=compressed,
        projection_evlrs=projection,
    )


def _read_header(path: Path) -> tuple[np.void, str]:
    """The public header block (a :data:`HEADER_13` or :data:`HEADER_14` record) and the
    version ``"1.3"`` or ``"1.4"``; raises :class:`LasWaveformError` for a file without the
    ``LASF`` signature, another version or a truncated header."""
    raw = _read_at(path, 0, HEADER_14.itemsize)
    if len(raw) < 4 or raw[:4] != LAS_SIGNATURE:
        raise fail(path, "not a LAS file (no 'LASF' signature)")
    if len(raw) < HEADER_13.itemsize:
        raise fail(path, f"truncated LAS header ({len(raw)} bytes)")
    major, minor = raw[24], raw[25]
    version = f"{major}.{minor}"
    if major != 1 or minor not in (3, 4):
        raise fail(path, f"LAS {version} has no waveform packets (LAS 1.3 or 1.4 expected)")
    if minor == 4 and len(raw) < HEADER_14.itemsize:
        raise fail(path, f"truncated LAS 1.4 header ({len(raw)} bytes)")
    dtype = HEADER_14 if minor == 4 else HEADER_13
    return np.frombuffer(raw[: dtype.itemsize], dtype)[0], version


def _point_layout(path: Path, hdr: np.void) -> tuple[int, int, int, bool]:
    """``(point_format, record_length, core_length, compressed)``: the waveform point format,
    the header's record length and the format's own length, bytes (the rest is extra bytes),
    and whether the point records are LAZ-compressed (bit 7 or 6 of the format byte).
    Raises :class:`LasWaveformError` for a format without waveform packets, or a record
    shorter than its format."""
    fmt_byte = int(hdr["point_format"])
    compressed = bool(fmt_byte & 0xC0)
    point_format = fmt_byte & 0x3F
    if point_format not in WAVEFORM_POINT_FORMATS:
        raise fail(
            path,
            f"point format {point_format} carries no waveform packets (formats 4, 5, 9 and 10 do); "
            "this is not a waveform LAS file",
        )
    record_length = int(hdr["point_record_length"])
    core_length = point_dtype(point_format).itemsize
    if record_length < core_length:
        raise fail(path, f"point record length {record_length} is shorter than point format {point_format} ({core_length} bytes)")
    return point_format, record_length, core_length, compressed


def _check_laz(path: Path, vlrs: list[tuple[int, np.void]]) -> None:
    """A LAZ file must carry the LASzip VLR (``laszip encoded``, record id 22204), and laspy
    needs a LAZ backend (lazrs, a dependency of waveforest, or laszip)."""
    if not any(bytes(h["user_id"]).rstrip(b"\0") == LASZIP_USER_ID and int(h["record_id"]) == LASZIP_RECORD_ID
               for _, h in vlrs):
        raise fail(path, "point data are LAZ-compressed (bit 7 of the point format byte) but the file has no LASzip VLR "
                         "('laszip encoded', record id 22204); the LAZ file is corrupt")
    if not laspy.LazBackend.detect_available():
        raise fail(path, "point data are LAZ-compressed and no LAZ backend is installed; "
                         "pip install 'laspy[lazrs]' (or decompress to LAS first)")


def _laz_end_of_points(path: Path, offset_to_points: int, file_size: int) -> int:
    """The first byte after a LAZ file's compressed points, as far as the file says it.

    LASzip writes the position of its chunk table in the 8 bytes at ``offset_to_point_data``;
    the table follows the compressed points, so that position bounds them. A position of -1
    (a streaming writer that never came back) or one outside the file gives the start of the
    points; then only the reader can tell where they end.
    """
    raw = _read_at(path, offset_to_points, 8)
    if len(raw) < 8:
        raise fail(path, f"truncated LAZ file: no compressed point data at byte {offset_to_points} ({file_size} bytes)")
    table = int(np.frombuffer(raw, "<i8")[0])
    return table if offset_to_points + 8 <= table <= file_size else offset_to_points + 8


def _scales_offsets(path: Path, hdr: np.void) -> tuple[np.ndarray, np.ndarray]:
    """(3,) float64 coordinate scales and offsets of the header, m; raises
    :class:`LasWaveformError` unless the scales are finite and non-zero, the offsets finite,
    and every int32 coordinate maps to a finite float64."""
    scales = np.asarray(hdr["scale"], dtype=np.float64).copy()
    offsets = np.asarray(hdr["offset"], dtype=np.float64).copy()
    if not np.all(np.isfinite(scales) & (scales != 0)):
        raise fail(path, f"header scale factors (x, y, z) are {scales.tolist()}; finite non-zero numbers expected")
    if not np.all(np.isfinite(offsets)):
        raise fail(path, f"header offsets (x, y, z) are {offsets.tolist()}; finite numbers expected")
    with np.errstate(over="ignore"):
        reach = 2.0**31 * np.abs(scales) + np.abs(offsets)  # largest |coordinate| an int32 record can give
    if not np.all(np.isfinite(reach)):
        raise fail(
            path,
            f"header scale factors {scales.tolist()} and offsets {offsets.tolist()} give coordinates beyond the "
            "float64 range; the header is corrupt",
        )
    return scales, offsets


def _laspy_dimensions(path: Path, prefix: bytes, point_format: int, record_length: int) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Point dimension names and extra-bytes dimension names as laspy reads them from the
    header and VLRs in ``prefix``; raises :class:`LasWaveformError` if laspy cannot, or if
    its record size differs from the header's ``record_length``."""
    try:
        with _laspy_logs_as_warnings(path), laspy.open(io.BytesIO(prefix), read_evlrs=False) as reader:
            pf = reader.header.point_format
            dim_names = tuple(pf.dimension_names)
            extra_names = tuple(pf.extra_dimension_names)
            pf_size = pf.size
    except Exception as exc:  # laspy raises many types for a broken header or VLRs
        raise fail(path, f"cannot read the LAS header and VLRs ({type(exc).__name__}: {exc})") from exc
    if pf_size != record_length:
        raise fail(path, f"point record length {record_length} does not match point format {point_format} ({pf_size} bytes)")
    return dim_names, extra_names


def _descriptors(path: Path, prefix: bytes, vlrs, evlrs) -> tuple[dict[int, WavePacketDescriptor], int | None]:
    """The wave packet descriptors (VLRs, and on LAS 1.4 EVLRs) by index, and the position of
    an EVLR waveform data record (None without). A descriptor VLR shorter than 26 bytes
    raises :class:`LasWaveformError`; a truncated descriptor EVLR is skipped."""
    descriptors: dict[int, WavePacketDescriptor] = {}
    for pos, h in vlrs:
        rid = int(h["record_id"])
        if bytes(h["user_id"]).rstrip(b"\0") == LASF_SPEC and WPD_FIRST_RECORD_ID <= rid <= WPD_LAST_RECORD_ID:
            if int(h["record_length"]) < WPD_BODY.itemsize:
                raise fail(path, f"waveform packet descriptor VLR {rid} has {int(h['record_length'])} bytes, 26 expected")
            body = prefix[pos + VLR_HEADER.itemsize : pos + VLR_HEADER.itemsize + WPD_BODY.itemsize]
            descriptors[rid - WPD_INDEX_OFFSET] = WavePacketDescriptor.from_body(rid - WPD_INDEX_OFFSET, body)

    # LAS 1.4: descriptors may be EVLRs; the waveform record may be one
    evlr_waveform = None
    for pos, h in evlrs:
        rid = int(h["record_id"])
        is_spec = bytes(h["user_id"]).rstrip(b"\0") == LASF_SPEC
        if is_spec and rid == WAVEFORM_RECORD_ID:
            evlr_waveform = pos
        elif is_spec and WPD_FIRST_RECORD_ID <= rid <= WPD_LAST_RECORD_ID:
            body = _read_at(path, pos + EVLR_HEADER.itemsize, WPD_BODY.itemsize)
            if len(body) == WPD_BODY.itemsize:
                descriptors[rid - WPD_INDEX_OFFSET] = WavePacketDescriptor.from_body(rid - WPD_INDEX_OFFSET, body)
    return descriptors, evlr_waveform


def _check_record_count(path: Path, what: str, n: int, header_bytes: int, space: int, after: str, before: str) -> None:
    """Raise :class:`LasWaveformError` if ``n`` record headers of ``header_bytes`` cannot fit
    in the ``space`` bytes between ``after`` and ``before`` (a corrupt count field)."""
    room = space // header_bytes
    if n > room:
        raise fail(
            path,
            f"number of {what}s is {n}, but at most {room} {what} headers ({header_bytes} bytes each) fit between "
            f"{after} and {before}; the header field is corrupt",
        )


def _read_vlrs(path: Path, hdr: np.void, version: str, file_size: int) -> tuple[bytes, list[tuple[int, np.void]]]:
    """The bytes before the point data and the VLR headers in them (position, header).

    The VLR count and each VLR's length are bounded by the header geometry before anything
    is read: the VLRs lie between ``header_size`` and ``offset_to_point_data``, 54 bytes of
    header each, so a corrupt count cannot make a reader loop or allocate without bound.
    """
    header_size = int(hdr["header_size"])
    offset = int(hdr["offset_to_point_data"])
    n_vlrs = int(hdr["number_of_vlrs"])
    if header_size < HEADER_SIZE[version]:
        raise fail(path, f"header size field is {header_size} bytes; a LAS {version} header has at least {HEADER_SIZE[version]}")
    if offset < header_size:
        raise fail(path, f"offset to point data ({offset}) lies inside the {header_size}-byte header")
    if offset > file_size:
        raise fail(path, f"truncated file: offset to point data is byte {offset}, but the file has {file_size} bytes")
    _check_record_count(path, "VLR", n_vlrs, VLR_HEADER.itemsize, offset - header_size,
                        f"the end of the header (byte {header_size})", f"the point data (byte {offset})")
    prefix = _read_at(path, 0, offset)
    vlrs, pos = [], header_size
    for k in range(n_vlrs):
        if pos + VLR_HEADER.itemsize > offset:
            raise fail(
                path,
                f"VLR {k + 1} of {n_vlrs} would start at byte {pos}, past the start of the point data (byte {offset}); "
                "the VLR count or a VLR's record length is corrupt",
            )
        h = np.frombuffer(prefix, VLR_HEADER, count=1, offset=pos)[0]
        end = pos + VLR_HEADER.itemsize + int(h["record_length"])
        if end > offset:
            raise fail(
                path,
                f"VLR {k + 1} of {n_vlrs} (record id {int(h['record_id'])}, at byte {pos}) declares {int(h['record_length'])} "
                f"bytes of data, which run past the start of the point data (byte {offset})",
            )
        vlrs.append((pos, h))
        pos = end
    return prefix, vlrs


_EB_NAME = (4, 32)
_EB_DESCRIPTION = (160, 32)
"""Position and size of the text fields in a 192-byte extra-bytes descriptor."""


def _utf8_text_fields(prefix: bytes, vlrs: list[tuple[int, np.void]]) -> tuple[bytes, list[str]]:
    """``prefix`` with '?' for the bytes of non-UTF-8 text fields that laspy decodes strictly.

    Returns the (possibly patched) bytes and the names of the fields patched. Covered: the
    VLR user ids and descriptions, and the names and descriptions of extra-bytes descriptors.
    """
    buf = bytearray(prefix)
    fixed: list[str] = []

    def fix(pos: int, size: int, what: str) -> None:
        raw = bytes(buf[pos : pos + size]).split(b"\0", 1)[0]
        try:
            raw.decode("utf-8")
        except UnicodeDecodeError:
            buf[pos : pos + len(raw)] = bytes(b if b < 0x80 else 0x3F for b in raw)
            fixed.append(what)

    for k, (pos, h) in enumerate(vlrs):
        fix(pos + 2, 16, f"VLR {k + 1} user id")
        fix(pos + 22, 32, f"VLR {k + 1} description")
        if bytes(h["user_id"]).rstrip(b"\0") == LASF_SPEC and int(h["record_id"]) == EXTRA_BYTES_RECORD_ID:
            body = pos + VLR_HEADER.itemsize
            for j in range(int(h["record_length"]) // EXTRA_BYTES_DESCRIPTOR.itemsize):
                at = body + j * EXTRA_BYTES_DESCRIPTOR.itemsize
                fix(at + _EB_NAME[0], _EB_NAME[1], f"extra-bytes descriptor {j + 1} name")
                fix(at + _EB_DESCRIPTION[0], _EB_DESCRIPTION[1], f"extra-bytes descriptor {j + 1} description")
    return bytes(buf), fixed


_EB_BASE_SIZES = (1, 1, 2, 2, 4, 4, 8, 8, 4, 8)
"""Bytes of the extra-bytes data types 1-10 (u1, i1, u2, i2, u4, i4, u8, i8, f4, f8)."""


def _extra_bytes_size(data_type: int, options: int) -> int | None:
    """Bytes one extra-bytes descriptor takes in a point record, None for an unknown type."""
    if data_type == 0:
        return options  # undocumented bytes: the options field holds their count
    if 1 <= data_type <= 30:  # 11-30: the deprecated 2- and 3-element arrays
        return _EB_BASE_SIZES[(data_type - 1) % 10] * ((data_type - 1) // 10 + 1)
    return None


def _check_extra_bytes(path: Path, prefix: bytes, vlrs: list[tuple[int, np.void]], point_format: int, extra: int) -> None:
    """The extra-bytes VLR against the record length: known data types, sizes that add up.

    ``extra`` is the record length less the point format's own bytes. Without an
    extra-bytes VLR any ``extra`` is fine (unregistered bytes); records without extra
    bytes make laspy ignore the VLR with a warning (a writer that dropped the bytes but
    kept the VLR).
    """
    ebs = [
        (pos, h) for pos, h in vlrs
        if bytes(h["user_id"]).rstrip(b"\0") == LASF_SPEC and int(h["record_id"]) == EXTRA_BYTES_RECORD_ID
    ]
    if not ebs:
        return
    if len(ebs) > 1:
        raise fail(path, f"{len(ebs)} extra-bytes VLRs (LASF_Spec, record id 4); one expected")
    pos, h = ebs[0]
    length = int(h["record_length"])
    if length % EXTRA_BYTES_DESCRIPTOR.itemsize:
        raise fail(path, f"the extra-bytes VLR has {length} bytes, not a multiple of {EXTRA_BYTES_DESCRIPTOR.itemsize} (one descriptor each)")
    body = np.frombuffer(prefix, EXTRA_BYTES_DESCRIPTOR, count=length // EXTRA_BYTES_DESCRIPTOR.itemsize, offset=pos + VLR_HEADER.itemsize)
    total, names = 0, set()
    for j, d in enumerate(body, start=1):
        name = bytes(d["name"]).split(b"\0", 1)[0]
        size = _extra_bytes_size(int(d["data_type"]), int(d["options"]))
        if size is None or size == 0:
            raise fail(
                path,
                f"extra-bytes descriptor {j} ({name.decode('ascii', 'replace')!r}) has data type {int(d['data_type'])} "
                f"(options {int(d['options'])}); data types 1-30, or 0 with a byte count in options, expected",
            )
        if not name or name in names:
            raise fail(path, f"extra-bytes descriptor {j} has {'an empty' if not name else 'a repeated'} name {name!r}; unique names expected")
        names.add(name)
        total += size
    if total != extra and extra > 0:  # extra == 0: laspy ignores the VLR, and says so (a warning)
        raise fail(
            path,
            f"the extra-bytes VLR describes {total} bytes per point, but the point record length leaves {extra} bytes "
            f"beyond point format {point_format}'s own",
        )


@contextlib.contextmanager
def _laspy_logs_as_warnings(path: Path) -> Iterator[None]:
    """Re-issue what laspy logs (e.g. a VLR it cannot parse) as warnings naming ``path``."""
    logger = logging.getLogger("laspy")

    class Handler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            warn(f"{path}: {record.getMessage()}")

    handler, propagate = Handler(logging.WARNING), logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def _evlr_headers(path: Path, hdr: np.void, file_size: int, end_of_points: int) -> list[tuple[int, np.void]]:
    """The EVLR headers of a LAS 1.4 file (position, header), their start and count checked.

    The first EVLR must start after the point records and every EVLR header (60 bytes)
    must fit in the file; an EVLR whose data run past the end of the file ends the walk
    with a warning (the points and any earlier EVLRs are still read).
    """
    n = int(hdr["number_of_evlrs"])
    if n == 0:
        return []
    start = int(hdr["start_of_first_evlr"])
    if start < end_of_points or start + EVLR_HEADER.itemsize > file_size:
        raise fail(
            path,
            f"number of EVLRs is {n}, but the start of the first EVLR is byte {start}; expected between the end of the "
            f"point records (byte {end_of_points}) and byte {file_size - EVLR_HEADER.itemsize} (60-byte EVLR header, "
            f"file of {file_size} bytes); the header's EVLR fields are corrupt",
        )
    _check_record_count(path, "EVLR", n, EVLR_HEADER.itemsize, file_size - start,
                        f"the first EVLR (byte {start})", f"the end of the file ({file_size} bytes)")
    out, pos = [], start
    for k in range(n):
        h = _record_header(path, pos, file_size)
        if h is None:
            warn(f"{path}: EVLR {k + 1} of {n} would start at byte {pos}, beyond the end of the file ({file_size} bytes); ignored")
            break
        out.append((pos, h))
        pos += EVLR_HEADER.itemsize + int(h["record_length"])
    return out


def _check_point_count(path: Path, hdr: np.void, n_points: int, record_length: int, file_size: int, evlrs) -> None:
    """Compare the header's point count with the room the file has for point records.

    The point records run from ``offset_to_point_data`` to the first of: a well-formed
    waveform data record, the first EVLR, the end of the file. A count of 0 on a file
    with room for records is an error, not an empty table: it is what a writer leaves when
    it dies before it updates the header, and reading "0 points" would hide that. Room for
    more records than the count announces is read on with a warning.
    """
    offset = int(hdr["offset_to_point_data"])
    end, what = file_size, "the end of the file"
    start_wf = int(hdr["start_of_waveform_data"])
    if offset <= start_wf < end and _is_waveform_header(_record_header(path, start_wf, file_size), file_size - start_wf):
        end, what = start_wf, f"the waveform data record (byte {start_wf})"
    if evlrs and offset <= evlrs[0][0] < end:
        end, what = evlrs[0][0], f"the first EVLR (byte {evlrs[0][0]})"
    room = max(0, end - offset) // record_length
    if n_points == 0 and room > 0:
        counts = "legacy and 64-bit point counts are" if "point_count" in hdr.dtype.names else "point count is"
        raise fail(
            path,
            f"the header's {counts} 0, but the {end - offset} bytes from the point data (byte {offset}) to {what} "
            f"hold {room} point records of {record_length} bytes; the header is corrupt or was never completed by its writer",
        )
    if n_points == 0:
        warn(f"{path}: the header announces 0 points; the file holds no pulses")
    elif room > n_points:
        warn(
            f"{path}: the header announces {n_points} points, but there is room for {room} point records of "
            f"{record_length} bytes before {what}; reading the first {n_points}"
        )


def open_point_reader(las: LasWaveformFile) -> laspy.LasReader:
    """A laspy reader of the point records of a checked file (its text fields patched if needed).

    What laspy logs while it parses the header again was reported when the file was
    opened, and is dropped here.
    """
    source = las.path if las.header_bytes is None else io.BufferedReader(_PatchedFile(las.path, las.header_bytes))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LasWaveformWarning)
        with _laspy_logs_as_warnings(las.path):
            return laspy.open(source, read_evlrs=False)


class _PatchedFile(io.RawIOBase):
    """A read-only file whose first bytes are replaced by ``head`` (same length)."""

    def __init__(self, path: Path, head: bytes):
        super().__init__()
        self._fh = open(path, "rb")
        self._head = head
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, pos: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: os.fstat(self._fh.fileno()).st_size}[whence]
        self._pos = max(0, base + pos)
        return self._pos

    def readinto(self, b) -> int:
        view = memoryview(b).cast("B")
        got = 0
        if self._pos < len(self._head):
            got = min(len(view), len(self._head) - self._pos)
            view[:got] = self._head[self._pos : self._pos + got]
        if got < len(view):
            self._fh.seek(self._pos + got)
            got += self._fh.readinto(view[got:]) or 0
        self._pos += got
        return got

    def close(self) -> None:
        self._fh.close()
        super().close()


def _locate_waveform_data(
    path: Path, file_size: int, ge: int, start_field: int, evlr_pos: int | None, end_of_points: int,
    compressed: bool = False,
) -> WaveformData:
    """Where the packets are: a ``.wdp`` beside the file, or the file's own waveform record.

    In a LAZ file an internal waveform record follows the compressed points, where the
    header's ``start_of_waveform_data`` (or an EVLR) says; its 60-byte record header must be
    well formed there, since a stale pointer (a LAZ writer that dropped the waveforms) would
    otherwise decode compressed point bytes as samples.
    """
    external, internal = bool(ge & GE_WAVEFORM_EXTERNAL), bool(ge & GE_WAVEFORM_INTERNAL)
    wdp = find_wdp(path)
    internal_pos = None
    if start_field and start_field + WAVEFORM_HEADER_SIZE <= file_size and _is_waveform_header(
        _record_header(path, start_field, file_size), file_size - start_field
    ):
        internal_pos = start_field
    elif evlr_pos is not None:
        internal_pos = evlr_pos
    elif start_field:
        internal_pos = start_field  # trusted below, with a warning if malformed
    wdz = next((c for c in map(path.with_suffix, (".wdz", ".WDZ", ".Wdz")) if c.is_file()), None)
    if wdp is None and wdz is not None and (external or internal_pos is None):
        raise fail(path, f"the waveform packets are in {wdz.name}, LASzip-compressed, which waveforest cannot read; "
                         f"decompress them first with LAStools: laszip -i {path.name} -o {path.stem}_wf.las "
                         f"(writes {path.stem}_wf.wdp beside it), then read {path.stem}_wf.las")
    if not external and not internal:
        if wdp is not None:
            warn(f"{path}: global encoding ({ge}) sets neither waveform bit; using {wdp.name} beside it")
            external = True
        elif internal_pos is not None:
            warn(f"{path}: global encoding ({ge}) sets neither waveform bit; using the waveform record at byte {internal_pos}")
            internal = True
        else:
            raise fail(path, f"no waveform data: global encoding ({ge}) sets neither bit 1 (internal) nor bit 2 (external), and there is no .wdp file")
    if external and (wdp is not None or not internal or internal_pos is None):
        if wdp is None:
            raise fail(path, f"waveform data are external (global encoding bit 2) but {path.with_suffix('.wdp').name} is missing")
        size = wdp.stat().st_size
        h = _record_header(wdp, 0, size)
        ok = _is_waveform_header(h, size) and int(h["record_length"]) == size - WAVEFORM_HEADER_SIZE
        if ok:
            pass
        elif size < WAVEFORM_HEADER_SIZE:
            warn(f"{wdp}: {size} bytes, shorter than its 60-byte waveform record header; trusting the points' "
                 "byte offsets and packet sizes")
        elif _is_waveform_record(h):  # the right record, of another length
            warn(f"{wdp}: its record header announces {int(h['record_length'])} bytes of waveform data, the file "
                 f"holds {size - WAVEFORM_HEADER_SIZE} after it (cut short, or bytes appended); trusting the points' "
                 "byte offsets and packet sizes")
        else:
            warn(f"{wdp}: malformed 60-byte waveform record header (expected user ID LASF_Spec and record ID "
                 "65535); trusting the points' byte offsets and packet sizes")
        return WaveformData(wdp, 0, size, "external", ok, int(h["record_length"]) if ok else 0)
    if internal_pos is None:
        if compressed:
            raise fail(path, _LAZ_NO_RECORD.format(start=start_field))
        raise fail(path, "waveform data are internal (global encoding bit 1) but the file has no waveform data packet record")
    if internal_pos < end_of_points:
        raise fail(path, f"the waveform data record (byte {internal_pos}) overlaps the point records (end at byte {end_of_points})")
    if internal_pos >= file_size:
        raise fail(path, f"truncated file: the waveform data record should start at byte {internal_pos}, but the file has {file_size} bytes")
    h = _record_header(path, internal_pos, file_size)
    ok = _is_waveform_header(h, file_size - internal_pos)
    if not ok and compressed:
        raise fail(path, _LAZ_NO_RECORD.format(start=internal_pos))
    if not ok:
        warn(f"{path}: malformed waveform record header at byte {internal_pos}; trusting the points' byte offsets and packet sizes")
    return WaveformData(path, internal_pos, file_size - internal_pos, "internal", ok, int(h["record_length"]) if ok else 0)


_LAZ_NO_RECORD = (
    "waveform data are internal (global encoding bit 1), but there is no waveform data packet record "
    "(60-byte header LASF_Spec / 65535) at byte {start}, where start_of_waveform_data points; in a LAZ file the "
    "record must follow the compressed points. Put the waveforms in a .wdp file beside the LAZ (same stem), "
    "or read the uncompressed LAS"
)


def resolve_attribute(las: LasWaveformFile, name: str | None) -> str | None:
    """The point dimension that ``name`` designates (exact, else unique case-insensitive match)."""
    if not name:
        return None
    if name in las.dimension_names:
        return name
    hits = [d for d in las.dimension_names if d.lower() == name.lower()]
    return hits[0] if len(hits) == 1 else None
