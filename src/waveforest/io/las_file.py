"""Open and check a LAS 1.3/1.4 waveform file: header, descriptors, waveform data location.

:func:`open_waveform_las` reads the public header block itself (numpy, so that the legacy
and 64-bit point counts and the waveform fields are seen as written), the VLRs through
laspy, and walks the EVLR headers of LAS 1.4 files without reading their bodies (the
waveform record may be gigabytes). It returns a :class:`LasWaveformFile`, or raises
:class:`.las_format.LasWaveformError` naming the file and the problem.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from .las_format import (
    EVLR_HEADER,
    GE_WAVEFORM_EXTERNAL,
    GE_WAVEFORM_INTERNAL,
    HEADER_13,
    HEADER_14,
    LAS_SIGNATURE,
    LASF_SPEC,
    WAVEFORM_HEADER_SIZE,
    WAVEFORM_POINT_FORMATS,
    WAVEFORM_RECORD_ID,
    WPD_BODY,
    WPD_FIRST_RECORD_ID,
    WPD_INDEX_OFFSET,
    WPD_LAST_RECORD_ID,
    LasWaveformError,
    WavePacketDescriptor,
    decode_text,
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


def _is_waveform_header(h: np.void | None, available: int) -> bool:
    return (
        h is not None
        and bytes(h["user_id"]).rstrip(b"\0") == LASF_SPEC
        and int(h["record_id"]) == WAVEFORM_RECORD_ID
        and int(h["record_length"]) <= available - WAVEFORM_HEADER_SIZE
    )


def find_wdp(path: Path) -> Path | None:
    """The ``.wdp`` file beside a LAS file (same stem), if there is one."""
    for suffix in (".wdp", ".WDP", ".Wdp"):
        cand = path.with_suffix(suffix)
        if cand.is_file():
            return cand
    return None


def open_waveform_las(path: str | os.PathLike) -> LasWaveformFile:
    """Check a LAS waveform file and describe it; raise :class:`LasWaveformError` if unusable.

    Checked here: LAS signature and version (1.3 or 1.4), a waveform point format (4, 5,
    9, 10), not LAZ-compressed, the point records all present (header count x record
    length fits in the file), the waveform data present (external ``.wdp`` or internal
    record, as the global encoding says). Per-point checks (descriptor index, packet
    bounds) happen while reading points. Header bounds and return counts are not checked:
    real files often carry those of a whole flight line.
    """
    path = Path(path)
    if not path.is_file():
        raise fail(path, "no such file")
    file_size = path.stat().st_size
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
    hdr = np.frombuffer(raw[: (HEADER_14 if minor == 4 else HEADER_13).itemsize], HEADER_14 if minor == 4 else HEADER_13)[0]
    fmt_byte = int(hdr["point_format"])
    if fmt_byte & 0xC0:
        raise fail(path, f"point data are LAZ-compressed (format byte {fmt_byte}); decompress to LAS first (e.g. laszip)")
    point_format = fmt_byte & 0x3F
    if point_format not in WAVEFORM_POINT_FORMATS:
        raise fail(
            path,
            f"point format {point_format} carries no waveform packets (formats 4, 5, 9 and 10 do); "
            "this is not a waveform LAS file",
        )
    record_length = int(hdr["point_record_length"])
    offset_to_points = int(hdr["offset_to_point_data"])
    legacy = int(hdr["legacy_point_count"])
    n_points = legacy
    by_return = np.asarray(hdr["legacy_points_by_return"], dtype=np.int64)
    if minor == 4:
        n_points = int(hdr["point_count"]) or legacy
        by_return = np.asarray(hdr["points_by_return"], dtype=np.int64)

    try:
        with laspy.open(path, read_evlrs=False) as reader:
            lh = reader.header
            vlrs = list(lh.vlrs)
            pf = lh.point_format
            dim_names = tuple(pf.dimension_names)
            extra_names = tuple(pf.extra_dimension_names)
            pf_size = pf.size
    except Exception as exc:  # laspy raises many types for a broken header or VLRs
        raise fail(path, f"cannot read the LAS header and VLRs ({exc})") from exc
    if pf_size != record_length:
        raise fail(path, f"point record length {record_length} does not match point format {point_format} ({pf_size} bytes)")

    end_of_points = offset_to_points + n_points * record_length
    if end_of_points > file_size:
        have = max(0, (file_size - offset_to_points) // record_length) if record_length else 0
        raise fail(
            path,
            f"truncated file: the header announces {n_points} points of {record_length} bytes from byte "
            f"{offset_to_points}, but the file has {file_size} bytes (room for {have} points)",
        )

    descriptors: dict[int, WavePacketDescriptor] = {}
    for v in vlrs:
        rid = int(v.record_id)
        if str(v.user_id).rstrip("\0") == LASF_SPEC.decode() and WPD_FIRST_RECORD_ID <= rid <= WPD_LAST_RECORD_ID:
            body = v.record_data_bytes()
            if len(body) < WPD_BODY.itemsize:
                raise fail(path, f"waveform packet descriptor VLR {rid} has {len(body)} bytes, 26 expected")
            descriptors[rid - WPD_INDEX_OFFSET] = WavePacketDescriptor.from_body(rid - WPD_INDEX_OFFSET, body)

    # LAS 1.4: walk the EVLR headers (descriptors may be EVLRs; find the waveform record)
    evlr_waveform = None
    if minor == 4 and int(hdr["number_of_evlrs"]) > 0:
        pos = int(hdr["start_of_first_evlr"])
        for _ in range(int(hdr["number_of_evlrs"])):
            h = _record_header(path, pos, file_size)
            if h is None:
                warn(f"{path}: EVLR header at byte {pos} lies beyond the end of the file ({file_size} bytes); ignored")
                break
            rid, length = int(h["record_id"]), int(h["record_length"])
            is_spec = bytes(h["user_id"]).rstrip(b"\0") == LASF_SPEC
            if is_spec and rid == WAVEFORM_RECORD_ID:
                evlr_waveform = pos
            elif is_spec and WPD_FIRST_RECORD_ID <= rid <= WPD_LAST_RECORD_ID:
                body = _read_at(path, pos + EVLR_HEADER.itemsize, WPD_BODY.itemsize)
                if len(body) == WPD_BODY.itemsize:
                    descriptors[rid - WPD_INDEX_OFFSET] = WavePacketDescriptor.from_body(rid - WPD_INDEX_OFFSET, body)
            pos += EVLR_HEADER.itemsize + length

    waveform = _locate_waveform_data(path, file_size, int(hdr["global_encoding"]), int(hdr["start_of_waveform_data"]), evlr_waveform, end_of_points)
    return LasWaveformFile(
        path=path,
        file_size=file_size,
        version=version,
        point_format=point_format,
        record_length=record_length,
        n_points=n_points,
        offset_to_point_data=offset_to_points,
        global_encoding=int(hdr["global_encoding"]),
        scales=np.asarray(hdr["scale"], dtype=np.float64).copy(),
        offsets=np.asarray(hdr["offset"], dtype=np.float64).copy(),
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
    )


def _locate_waveform_data(
    path: Path, file_size: int, ge: int, start_field: int, evlr_pos: int | None, end_of_points: int
) -> WaveformData:
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
        if not ok:
            warn(
                f"{wdp}: malformed 60-byte waveform record header (expected LASF_Spec / 65535 / record length "
                f"{size - WAVEFORM_HEADER_SIZE}); trusting the points' byte offsets and packet sizes"
            )
        return WaveformData(wdp, 0, size, "external", ok, int(h["record_length"]) if ok else 0)
    if internal_pos is None:
        raise fail(path, "waveform data are internal (global encoding bit 1) but the file has no waveform data packet record")
    if internal_pos < end_of_points:
        raise fail(path, f"the waveform data record (byte {internal_pos}) overlaps the point records (end at byte {end_of_points})")
    if internal_pos >= file_size:
        raise fail(path, f"truncated file: the waveform data record should start at byte {internal_pos}, but the file has {file_size} bytes")
    h = _record_header(path, internal_pos, file_size)
    ok = _is_waveform_header(h, file_size - internal_pos)
    if not ok:
        warn(f"{path}: malformed waveform record header at byte {internal_pos}; trusting the points' byte offsets and packet sizes")
    return WaveformData(path, internal_pos, file_size - internal_pos, "internal", ok, int(h["record_length"]) if ok else 0)


def resolve_attribute(las: LasWaveformFile, name: str | None) -> str | None:
    """The point dimension that ``name`` designates (exact, else unique case-insensitive match)."""
    if not name:
        return None
    if name in las.dimension_names:
        return name
    hits = [d for d in las.dimension_names if d.lower() == name.lower()]
    return hits[0] if len(hits) == 1 else None
