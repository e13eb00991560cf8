"""The binary layout of LAS 1.3/1.4 files with waveform packets (ASPRS LAS 1.4 R15).

One place for the byte layouts that both the reader (:mod:`waveforest.io.las.read`) and the writer
(:mod:`waveforest.io.las.write`) use: the public header block, (extended) variable length record
headers, the Waveform Packet Descriptor (WPD) body, the Extra Bytes descriptor, and the
point data records of the waveform point formats 4, 5, 9 and 10.

Waveform facts from the spec that the code relies on
----------------------------------------------------
- A WPD is a VLR (or EVLR) of user id ``LASF_Spec`` and record id ``99 + index``,
  ``index`` = 1..255 (record ids 100..354). Its 26-byte body: bits per sample (u8),
  compression type (u8, 0 = none), number of samples (u32), temporal sample spacing
  (u32, ps), digitizer gain and offset (f64; volts = offset + gain * DN).
- A point's wave packet fields: descriptor index (u8, 0 = no waveform), byte offset to
  the waveform data (u64), packet size in bytes (u32), return point waveform location
  ``L`` (f32, ps from the first sample), and x(t), y(t), z(t) (f32, m/ps).
- The byte offset counts from the start of the Waveform Data Packet Record *including
  its 60-byte header*: for data inside the LAS file from the header field "start of
  waveform data packet record" (LAS 1.3) or the EVLR of record id 65535 (LAS 1.4); for
  an external ``.wdp`` file beside the LAS file, from the start of that file (which
  begins with the same 60-byte header). The first packet is thus at offset 60.
- Global encoding bit 1: waveform data internal (deprecated in 1.4); bit 2: external.
- Geometry: the first sample of the packet lies at ``P + L * (x(t), y(t), z(t))``, where
  ``P`` is the point's XYZ; (x(t), y(t), z(t)) points from the target back toward the
  sensor and has the length of c/2 per picosecond. The real RIEGL file of the test data
  follows this sign (its README), and so does our writer.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from waveforest.errors import WaveforestError, WaveforestWarning

LAS_SIGNATURE = b"LASF"
LASF_SPEC = b"LASF_Spec"
LASF_PROJECTION = b"LASF_Projection"
"""User ID of the coordinate-system records (WKT 2112, GeoTIFF keys 34735-34737)."""
MAX_PROJECTION_BYTES = 1 << 20
"""Largest coordinate-system record read; a bigger one is not a CRS."""
WAVEFORM_RECORD_ID = 65535
"""Record id of the Waveform Data Packet Record (an EVLR, or the header of a ``.wdp``)."""
WPD_FIRST_RECORD_ID = 100
WPD_LAST_RECORD_ID = 354
WPD_INDEX_OFFSET = 99
"""Descriptor index = record id - 99 (1..255)."""
EXTRA_BYTES_RECORD_ID = 4
WKT_RECORD_ID = 2112
GEOKEY_DIRECTORY_RECORD_ID = 34735
GEOASCII_PARAMS_RECORD_ID = 34737
LASZIP_USER_ID = b"laszip encoded"
LASZIP_RECORD_ID = 22204
"""The LASzip VLR that every LAZ file carries (compressor, chunk size, items)."""

WAVEFORM_HEADER_SIZE = 60
"""Bytes of the Waveform Data Packet Record header (an EVLR header)."""

GE_GPS_STANDARD = 1 << 0
GE_WAVEFORM_INTERNAL = 1 << 1
GE_WAVEFORM_EXTERNAL = 1 << 2
GE_SYNTHETIC_RETURNS = 1 << 3
GE_WKT = 1 << 4

WAVEFORM_POINT_FORMATS = (4, 5, 9, 10)
"""Point data record formats that carry wave packet fields."""
FORMATS_BY_VERSION = {"1.3": (4, 5), "1.4": (4, 5, 9, 10)}
MAX_RETURNS = {4: 7, 5: 7, 9: 15, 10: 15}
"""Largest return number a point format can store (3 or 4 bits)."""

HEADER_SIZE = {"1.3": 235, "1.4": 375}

SCAN_ANGLE_UNIT_DEG = 0.006
"""Scan angle unit of point formats 6-10, degrees (formats 0-5 store whole degrees)."""

SUPPORTED_COMPRESSION = (0,)
"""Waveform compression types this package decodes (0 = uncompressed)."""


def sample_bytes(bits: int) -> int | None:
    """Bytes per stored sample for ``bits`` per sample, or None when not byte-aligned.

    Samples of 1-8 bits are stored one per byte, 9-16 in two bytes and 25-32 in four
    bytes (little-endian unsigned integers), as in LASlib; bit-packed layouts are not
    supported.
    """
    if 1 <= bits <= 8:
        return 1
    if 9 <= bits <= 16:
        return 2
    if 25 <= bits <= 32:
        return 4
    return None


class LasWaveformError(WaveforestError):
    """A LAS waveform file that cannot be read (or a table that cannot be written as one)."""


class LasWaveformWarning(WaveforestWarning):
    """Something odd but readable in a LAS waveform file (the data are still trusted)."""


def warn(message: str) -> None:
    """Issue a :class:`LasWaveformWarning` attributed to the caller's caller."""
    warnings.warn(message, LasWaveformWarning, stacklevel=3)


# -- header ---------------------------------------------------------------------------

_HEADER_13_FIELDS = [
    ("signature", "S4"),
    ("file_source_id", "<u2"),
    ("global_encoding", "<u2"),
    ("guid1", "<u4"),
    ("guid2", "<u2"),
    ("guid3", "<u2"),
    ("guid4", "S8"),
    ("version_major", "u1"),
    ("version_minor", "u1"),
    ("system_identifier", "S32"),
    ("generating_software", "S32"),
    ("creation_day", "<u2"),
    ("creation_year", "<u2"),
    ("header_size", "<u2"),
    ("offset_to_point_data", "<u4"),
    ("number_of_vlrs", "<u4"),
    ("point_format", "u1"),
    ("point_record_length", "<u2"),
    ("legacy_point_count", "<u4"),
    ("legacy_points_by_return", "<u4", (5,)),
    ("scale", "<f8", (3,)),
    ("offset", "<f8", (3,)),
    ("max_x", "<f8"),
    ("min_x", "<f8"),
    ("max_y", "<f8"),
    ("min_y", "<f8"),
    ("max_z", "<f8"),
    ("min_z", "<f8"),
    ("start_of_waveform_data", "<u8"),
]
HEADER_13 = np.dtype(_HEADER_13_FIELDS)
HEADER_14 = np.dtype(
    _HEADER_13_FIELDS
    + [
        ("start_of_first_evlr", "<u8"),
        ("number_of_evlrs", "<u4"),
        ("point_count", "<u8"),
        ("points_by_return", "<u8", (15,)),
    ]
)
assert HEADER_13.itemsize == HEADER_SIZE["1.3"] and HEADER_14.itemsize == HEADER_SIZE["1.4"]

VLR_HEADER = np.dtype(
    [("reserved", "<u2"), ("user_id", "S16"), ("record_id", "<u2"), ("record_length", "<u2"), ("description", "S32")]
)
EVLR_HEADER = np.dtype(
    [("reserved", "<u2"), ("user_id", "S16"), ("record_id", "<u2"), ("record_length", "<u8"), ("description", "S32")]
)
assert VLR_HEADER.itemsize == 54 and EVLR_HEADER.itemsize == WAVEFORM_HEADER_SIZE

WPD_BODY = np.dtype(
    [
        ("bits_per_sample", "u1"),
        ("compression", "u1"),
        ("number_of_samples", "<u4"),
        ("temporal_spacing_ps", "<u4"),
        ("digitizer_gain", "<f8"),
        ("digitizer_offset", "<f8"),
    ]
)
assert WPD_BODY.itemsize == 26

EXTRA_BYTES_DESCRIPTOR = np.dtype(
    [
        ("reserved", "<u2"),
        ("data_type", "u1"),
        ("options", "u1"),
        ("name", "S32"),
        ("unused", "S4"),
        ("no_data", "<f8", (3,)),
        ("min", "<f8", (3,)),
        ("max", "<f8", (3,)),
        ("scale", "<f8", (3,)),
        ("offset", "<f8", (3,)),
        ("description", "S32"),
    ]
)
assert EXTRA_BYTES_DESCRIPTOR.itemsize == 192
EXTRA_BYTES_FLOAT64 = 10
"""Extra-bytes data type code of a float64 value."""


@dataclass(frozen=True)
class WavePacketDescriptor:
    """One Waveform Packet Descriptor (LAS 1.4 R15, Table 20).

    Attributes
    ----------
    index : int
        1..255, the value points store in their descriptor index field.
    bits : int
        Bits per sample.
    compression : int
        Waveform compression type (0 = none).
    n_samples : int
        Samples per packet.
    spacing_ps : int
        Temporal sample spacing, ps.
    gain, offset : float
        Digitizer gain (volts per DN) and offset (volts at DN 0).
    """

    index: int
    bits: int
    compression: int
    n_samples: int
    spacing_ps: int
    gain: float
    offset: float

    @property
    def empty(self) -> bool:
        """A placeholder that describes no waveform (0 samples or 0 spacing)."""
        return self.n_samples == 0 or self.spacing_ps == 0

    @property
    def bytes_per_sample(self) -> int | None:
        return sample_bytes(self.bits)

    @property
    def packet_bytes(self) -> int | None:
        """Bytes of one packet, or None if the sample layout is unsupported."""
        b = self.bytes_per_sample
        return None if b is None else b * self.n_samples

    def body(self) -> bytes:
        """The 26-byte VLR body."""
        rec = np.zeros((), WPD_BODY)
        rec["bits_per_sample"] = self.bits
        rec["compression"] = self.compression
        rec["number_of_samples"] = self.n_samples
        rec["temporal_spacing_ps"] = self.spacing_ps
        rec["digitizer_gain"] = self.gain
        rec["digitizer_offset"] = self.offset
        return rec.tobytes()

    @classmethod
    def from_body(cls, index: int, body: bytes) -> WavePacketDescriptor:
        rec = np.frombuffer(body[: WPD_BODY.itemsize], WPD_BODY)[0]
        return cls(
            index=int(index),
            bits=int(rec["bits_per_sample"]),
            compression=int(rec["compression"]),
            n_samples=int(rec["number_of_samples"]),
            spacing_ps=int(rec["temporal_spacing_ps"]),
            gain=float(rec["digitizer_gain"]),
            offset=float(rec["digitizer_offset"]),
        )


def point_dtype(point_format: int, extra: list[tuple[str, str]] | None = None) -> np.dtype:
    """Packed numpy dtype of one point data record of a waveform point format.

    Field names follow laspy's raw names (``bit_fields`` holds the packed return
    numbers). ``extra`` appends extra-bytes fields ``(name, numpy type)``.
    """
    core = [("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2")]
    if point_format in (4, 5):
        core += [
            ("bit_fields", "u1"),  # return number 0-2, number of returns 3-5, scan dir 6, edge 7
            ("classification", "u1"),
            ("scan_angle_rank", "i1"),
            ("user_data", "u1"),
            ("point_source_id", "<u2"),
            ("gps_time", "<f8"),
        ]
        if point_format == 5:
            core += [("red", "<u2"), ("green", "<u2"), ("blue", "<u2")]
    elif point_format in (9, 10):
        core += [
            ("bit_fields", "u1"),  # return number 0-3, number of returns 4-7
            ("classification_flags", "u1"),
            ("classification", "u1"),
            ("user_data", "u1"),
            ("scan_angle", "<i2"),
            ("point_source_id", "<u2"),
            ("gps_time", "<f8"),
        ]
        if point_format == 10:
            core += [("red", "<u2"), ("green", "<u2"), ("blue", "<u2"), ("nir", "<u2")]
    else:
        raise ValueError(f"point format {point_format} has no wave packet fields")
    core += [
        ("wavepacket_index", "u1"),
        ("wavepacket_offset", "<u8"),
        ("wavepacket_size", "<u4"),
        ("return_point_wave_location", "<f4"),
        ("x_t", "<f4"),
        ("y_t", "<f4"),
        ("z_t", "<f4"),
    ]
    return np.dtype(core + list(extra or []))


def pack_return_bits(point_format: int, return_number: np.ndarray, number_of_returns: np.ndarray,
                     scan_flags: np.ndarray | int = 0) -> np.ndarray:
    """The packed return-number byte of a point format; in point formats 4 and 5 it also holds
    the scan direction flag and edge of flight line (``scan_flags`` bits 0 and 1), which point
    formats 9 and 10 keep in :func:`pack_scan_bits`'s byte."""
    rn = np.asarray(return_number, dtype=np.uint8)
    nr = np.asarray(number_of_returns, dtype=np.uint8)
    if point_format in (4, 5):
        return (rn & 0x07) | ((nr & 0x07) << 3) | ((np.asarray(scan_flags, np.uint8) & 0x03) << 6)
    return (rn & 0x0F) | ((nr & 0x0F) << 4)


def pack_scan_bits(scan_flags: np.ndarray) -> np.ndarray:
    """The classification-flags byte of point formats 9 and 10 with the scan direction flag
    (bit 6) and edge of flight line (bit 7) from ``scan_flags`` bits 0 and 1 (other flags 0)."""
    return ((np.asarray(scan_flags, np.uint8) & 0x03) << 6).astype(np.uint8)


def text_field(value: str, size: int) -> bytes:
    """An ASCII text field of ``size`` bytes, NUL padded (longer text is cut)."""
    raw = value.encode("ascii", errors="replace")[:size]
    return raw + b"\0" * (size - len(raw))


def decode_text(raw: bytes) -> str:
    """A NUL-padded text field as a str."""
    return bytes(raw).split(b"\0", 1)[0].decode("ascii", errors="replace").strip()
