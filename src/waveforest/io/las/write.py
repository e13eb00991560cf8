"""Write pulse tables as LAS 1.3/1.4 files with waveform packets (formats 4, 5, 9, 10).

The inverse of :mod:`waveforest.io.las.read`: each pulse of a pulse table (:data:`waveforest.io.pulses.PULSE_SCHEMA`)
becomes one waveform packet and one LAS point per DR echo. The virtual campaign writes its
data with it, and the tests write every layout real sensors produce (e.g. the Leica ALS60's
LAS 1.3 point format 4 with 8-bit, 256-sample packets).

Per echo ``i`` (return order) of a pulse the point carries

- X, Y, Z = ``echo_x/_y/_z[i]`` (quantised by the header scales), ``gps_time`` of the pulse,
  return number ``i + 1`` and number of returns = ``n_echoes``;
- intensity = ``echo_intensity[i]`` (rounded, clipped to 0..65535), scan angle of the pulse
  (whole degrees in formats 4/5, 0.006 deg units in 9/10), classification 0; the scan
  direction flag and edge of flight line from the optional column ``scan_flags``, the point
  source ID from ``point_source_id`` (else 0);
- the AGC of the pulse in ``user_data`` (rounded, clipped to 0..255; NaN -> 0) or, when
  ``agc_attribute`` names anything else, in a float64 extra-bytes dimension of that name;
- the wave packet of the pulse: descriptor index, byte offset, size, return point
  location ``L = echo_time_ns[i] * 1000`` ps, and
  ``(x(t), y(t), z(t)) = -dir * RANGE_PER_NS / 1000`` m/ps, so that the LAS relation
  ``anchor = P + L * (x(t), y(t), z(t))`` gives back the first-sample position.

One descriptor is written per distinct (samples, spacing, digitizer gain, digitizer offset)
in order of first appearance (at most 255). Waveform bytes are little-endian unsigned
``bits``-bit integers, uncompressed, either inside the file (LAS 1.4: EVLR 65535 after the
points; LAS 1.3: after the points at the header's "start of waveform data packet record",
global encoding bit 1) or in a ``.wdp`` file beside it (bit 2) that starts with the same
60-byte record header. Nothing time-dependent is written (creation day/year are arguments,
:func:`creation_today` the caller's choice), so the same table gives byte-identical files.

The coordinate system is an OGC WKT record (2112). LAS 1.3 predates WKT and asks for GeoTIFF
keys: a 1.3 file also gets a GeoKeyDirectory (34735) from the WKT (:func:`geokeys`), with the
EPSG code of a projected or geographic WKT, else a user-defined model with the WKT's name as
its citation (GeoAsciiParams, 34737).

What LAS cannot hold is refused with :class:`waveforest.io.las.format.LasWaveformError`, never
silently changed: samples that are not whole numbers in ``[0, 2**bits - 1]``, a sampling
interval that is not a whole number of picoseconds, a pulse without DR echo (no point to
carry its packet) or with more echoes than the point format's return number holds, two
pulses with one ``gps_time`` within a chunk (a reader would merge them), and echoes farther
than :data:`GEOMETRY_TOL_M` from ``anchor + dir * echo_time_ns * RANGE_PER_NS``. A pulse
with an empty ``samples`` list is written with descriptor index 0 (no waveform).

The writer streams: :class:`WaveformLasWriter` takes the table in chunks and holds only one
chunk in memory; points and packets go to temporary files beside the output, which are
assembled and renamed onto the final names in :meth:`WaveformLasWriter.close` (a failure
leaves nothing behind).
"""

from __future__ import annotations

import errno
import os
import re
import shutil
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import pyarrow as pa

from waveforest.atomic import make_temp, output_folder, publish
from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.las.format import (
    EVLR_HEADER,
    EXTRA_BYTES_DESCRIPTOR,
    EXTRA_BYTES_FLOAT64,
    EXTRA_BYTES_RECORD_ID,
    FORMATS_BY_VERSION,
    GE_GPS_STANDARD,
    GE_WAVEFORM_EXTERNAL,
    GE_WAVEFORM_INTERNAL,
    GE_WKT,
    GEOASCII_PARAMS_RECORD_ID,
    GEOKEY_DIRECTORY_RECORD_ID,
    HEADER_13,
    HEADER_14,
    LAS_SIGNATURE,
    LASF_PROJECTION,
    LASF_SPEC,
    MAX_RETURNS,
    SCAN_ANGLE_UNIT_DEG,
    VLR_HEADER,
    WAVEFORM_HEADER_SIZE,
    WAVEFORM_RECORD_ID,
    WKT_RECORD_ID,
    WPD_INDEX_OFFSET,
    LasWaveformError,
    WavePacketDescriptor,
    pack_return_bits,
    pack_scan_bits,
    point_dtype,
    text_field,
)
from waveforest.io.pulses import check_pulses

GEOMETRY_TOL_M = 0.01
"""Largest allowed distance between an echo's XYZ and ``anchor + dir * t * RANGE_PER_NS``, m.

LAS stores each echo's XYZ and its time ``L`` in the packet; the first-sample position is
derived from them, so a table whose echoes are not on their beam cannot be represented."""

DIR_NORM_TOL = 1e-6
"""Largest allowed deviation of ``|dir|`` from 1."""

SPACING_TOL_PS = 1e-3
"""``sampling_ns * 1000`` must be this close to a whole number of picoseconds."""

MAX_DESCRIPTORS = 255
COPY_BUFFER_BYTES = 16 << 20
DEFAULT_CREATION = (1, 2014)
"""Creation day of year and year written when none is given (no clock is read)."""

GEOKEY_MODEL, GEOKEY_RASTER, GEOKEY_CITATION = 1024, 1025, 1026
GEOKEY_GEOGRAPHIC, GEOKEY_PROJECTED, GEOKEY_LINEAR_UNITS = 2048, 3072, 3076
"""GeoTIFF key ids (GeoTIFF 1.0 §6.3): model type, raster type, citation, EPSG codes, units."""
USER_DEFINED = 32767
METRE = 9001


def creation_today() -> tuple[int, int]:
    """(day of year, year) of today in UTC, or of ``SOURCE_DATE_EPOCH`` (seconds since 1970,
    the reproducible-builds convention) when that is set."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    if epoch and not epoch.strip().isdigit():
        raise WaveforestError(f"SOURCE_DATE_EPOCH={epoch!r}: expected whole seconds since 1970-01-01 UTC")
    day = (datetime.fromtimestamp(int(epoch), UTC) if epoch else datetime.now(UTC)).date()
    return day.timetuple().tm_yday, day.year


WKT_CRS = {"PROJCS", "PROJCRS", "PROJECTEDCRS", "LOCAL_CS", "ENGCRS", "ENGINEERINGCRS", "COMPD_CS", "COMPOUNDCRS",
           "GEOGCS", "GEOGCRS", "GEOGRAPHICCRS", "GEODCRS", "GEODETICCRS", "GEOCCS", "VERT_CS", "VERTCRS",
           "VERTICALCRS", "BOUNDCRS"}
"""Top-level keywords of an OGC WKT 1 or 2 coordinate reference system."""


def wkt_problem(wkt: str, metric: bool = False) -> str | None:
    """What keeps ``wkt`` from being the OGC WKT of a CRS (a keyword of :data:`WKT_CRS`, then
    brackets and quotes that close), or with ``metric`` from holding coordinates in metres (a
    geographic CRS: degrees); None when nothing does."""
    text = wkt.strip()
    kind = re.match(r"([A-Za-z_]+)\s*[\[(]", text)
    if kind is None or kind.group(1).upper() not in WKT_CRS:
        return (f"expected OGC WKT of a coordinate reference system (PROJCS[...], PROJCRS[...], ...), got "
                f"{text[:40]!r}{'...' if len(text) > 40 else ''}")
    depth, quoted = 0, False
    for ch in text:
        if ch == '"':
            quoted = not quoted
        elif not quoted and ch in "[(":
            depth += 1
        elif not quoted and ch in "])":
            depth -= 1
            if depth < 0:
                break
    if depth or quoted:
        return "expected OGC WKT whose brackets and quotes close"
    top = kind.group(1).upper()
    if metric and (top in ("GEOGCS", "GEOGCRS", "GEOGRAPHICCRS") or (top in ("GEODCRS", "GEODETICCRS")
                                                                    and "ELLIPSOIDAL" in text.upper())):
        return ("a geographic CRS gives coordinates in degrees, but the scene's are metres; expected a projected "
                "or local CRS")
    return None


def geokeys(wkt: str) -> tuple[bytes, bytes]:
    """GeoKeyDirectory and GeoAsciiParams bodies (uint16 records, ``|``-terminated ASCII) of an
    OGC WKT (1 or 2): projected or geographic with the EPSG code of its top-level AUTHORITY / ID,
    else user-defined, in metres, with the WKT's name as citation (its key counts the ``|``)."""
    text = wkt.strip()
    kind = text.split("[", 1)[0].strip().upper()
    code = re.search(r'(?:AUTHORITY|ID)\[\s*"EPSG"\s*,\s*"?(\d+)"?\s*\]\s*\]\s*$', text, re.IGNORECASE)
    name = re.match(r'[A-Z_]+\[\s*"([^"]*)"', text, re.IGNORECASE)
    citation = ((name.group(1) if name else "unnamed").replace("|", "/") + "|").encode("ascii", "replace")
    keys = [(GEOKEY_MODEL, 0, 1, USER_DEFINED), (GEOKEY_RASTER, 0, 1, 1),
            (GEOKEY_CITATION, GEOASCII_PARAMS_RECORD_ID, len(citation), 0)]
    if code and kind in ("PROJCS", "PROJCRS", "PROJECTEDCRS"):
        keys[0] = (GEOKEY_MODEL, 0, 1, 1)
        keys += [(GEOKEY_PROJECTED, 0, 1, int(code.group(1))), (GEOKEY_LINEAR_UNITS, 0, 1, METRE)]
    elif code and kind in ("GEOGCS", "GEOGCRS", "GEOGRAPHICCRS"):
        keys[0] = (GEOKEY_MODEL, 0, 1, 2)
        keys.append((GEOKEY_GEOGRAPHIC, 0, 1, int(code.group(1))))
    else:
        keys.append((GEOKEY_LINEAR_UNITS, 0, 1, METRE))
    body = np.array([(1, 1, 0, len(keys))] + sorted(keys), "<u2")
    return body.tobytes(), citation + b"\0"  # LAS: NUL-separated strings


@dataclass(frozen=True)
class _Chunk:
    """One chunk of a pulse table as arrays: n pulses, m echoes (flat, pulse order)."""

    n: int
    pulse_id: np.ndarray  # (n,)
    gps: np.ndarray  # (n,) s
    direction: np.ndarray  # (n, 3) unit vectors
    anchor: np.ndarray  # (n, 3) m
    sampling_ns: np.ndarray  # (n,) ns
    gain: np.ndarray  # (n,)
    dig_offset: np.ndarray  # (n,)
    scan: np.ndarray  # (n,) deg
    scan_flags: np.ndarray  # (n,) uint8: bit 0 scan direction flag, bit 1 edge of flight line
    source_id: np.ndarray  # (n,) uint16 point source ID (flight line)
    agc: np.ndarray  # (n,)
    samples: np.ndarray  # flat samples of every pulse
    s_off: np.ndarray  # (n + 1,) offsets into samples
    n_samples: np.ndarray  # (n,)
    echo_xyz: np.ndarray  # (m, 3) m
    et: np.ndarray  # (m,) echo time, ns
    ei: np.ndarray  # (m,) echo intensity
    e_off: np.ndarray  # (n + 1,) offsets into the echoes
    n_echo: np.ndarray  # (n,)
    has_wf: np.ndarray  # (n,) bool: the pulse has samples
    pulse_of_echo: np.ndarray  # (m,) pulse row of each echo
    wf_echo: np.ndarray  # (m,) bool: the echo's pulse has samples


def _optional(table: pa.Table, name: str, dtype) -> np.ndarray:
    """Column ``name`` as ``dtype``, or zeros where the table has no such column."""
    if name not in table.column_names:
        return np.zeros(table.num_rows, dtype)
    return table.column(name).to_numpy().astype(dtype)


def _list_column(table: pa.Table, name: str) -> tuple[np.ndarray, np.ndarray]:
    """Flat values and (n + 1,) int64 offsets of a list column."""
    col = table.column(name)
    arr = col.combine_chunks() if col.num_chunks != 1 else col.chunk(0)
    offsets = arr.offsets.to_numpy().astype(np.int64)
    flat = arr.flatten().to_numpy(zero_copy_only=False)
    return flat, offsets - offsets[0]


def _vlr(user_id: bytes, record_id: int, body: bytes, description: str) -> bytes:
    head = np.zeros((), VLR_HEADER)
    head["user_id"] = user_id
    head["record_id"] = record_id
    head["record_length"] = len(body)
    head["description"] = text_field(description, 32)
    return head.tobytes() + body


def _waveform_record_header(n_bytes: int) -> bytes:
    head = np.zeros((), EVLR_HEADER)
    head["user_id"] = LASF_SPEC
    head["record_id"] = WAVEFORM_RECORD_ID
    head["record_length"] = n_bytes
    head["description"] = text_field("Waveform data packets", 32)
    return head.tobytes()


GPS_WEEK_S = 604800.0
"""Seconds in a GPS week: GPS week time lies in [0, GPS_WEEK_S)."""

GPS_TIME_TYPES = ("week", "standard")
"""Values of :class:`WaveformLasWriter`'s ``gps_time_type``."""


class WaveformLasWriter:
    """Stream pulse tables into a LAS waveform file; use as a context manager.

    Parameters
    ----------
    path : str or Path
        Output ``.las`` file. With ``storage="external"`` the packets go to
        ``path.with_suffix(".wdp")``.
    version : {"1.4", "1.3"}
    point_format : int, optional
        4 or 5 (LAS 1.3 and 1.4), 9 or 10 (LAS 1.4). Default 9 for 1.4, 4 for 1.3.
    bits : {8, 16}
        Bits per waveform sample; samples must be whole numbers in ``[0, 2**bits - 1]``.
    storage : {"internal", "external"}
    agc_attribute : str or None
        ``"user_data"`` (8 bit), another name (a float64 extra-bytes dimension), or None
        (no AGC written; ``user_data`` is 0).
    scales : (3,) float
        Coordinate scales, m (0.001 = mm).
    offsets : (3,) float, optional
        Coordinate offsets, m; default: the minima of the first chunk's echoes, floored
        to whole kilometres.
    system_identifier, generating_software : str
        Header text (at most 32 characters).
    creation : (int, int)
        File creation day of year and year.
    file_source_id : int
        Header file source id (e.g. the flight-line number).
    wkt : str, optional
        OGC WKT of the coordinate system (written as a ``LASF_Projection`` 2112 VLR).
    gps_time_type : {"week", "standard"}
        What ``gps_time`` holds: seconds into the GPS week (below 604,800), or adjusted
        standard GPS time (GPS seconds - 1e9; global encoding bit 0).

    Examples
    --------
    >>> with WaveformLasWriter("line.las", bits=8) as w:    # doctest: +SKIP
    ...     for chunk in chunks:
    ...         w.write(chunk)
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        version: str = "1.4",
        point_format: int | None = None,
        bits: int = 8,
        storage: str = "internal",
        agc_attribute: str | None = "user_data",
        scales: tuple[float, float, float] = (0.001, 0.001, 0.001),
        offsets: tuple[float, float, float] | None = None,
        system_identifier: str = "waveforest",
        generating_software: str = "waveforest",
        creation: tuple[int, int] = DEFAULT_CREATION,
        file_source_id: int = 0,
        wkt: str | None = None,
        gps_time_type: str = "week",
    ) -> None:
        version = str(version)
        if gps_time_type not in GPS_TIME_TYPES:
            raise ValueError(f"gps_time_type must be one of {', '.join(GPS_TIME_TYPES)}, got {gps_time_type!r}")
        if version not in FORMATS_BY_VERSION:
            raise ValueError(f"version must be '1.3' or '1.4', got {version!r}")
        if point_format is None:
            point_format = 9 if version == "1.4" else 4
        if point_format not in FORMATS_BY_VERSION[version]:
            raise ValueError(
                f"LAS {version} waveform point formats are {FORMATS_BY_VERSION[version]}, got {point_format}"
            )
        if bits not in (8, 16):
            raise ValueError(f"bits must be 8 or 16, got {bits}")
        if storage not in ("internal", "external"):
            raise ValueError(f"storage must be 'internal' or 'external', got {storage!r}")
        scales = np.asarray(scales, dtype=np.float64)
        if scales.shape != (3,) or not np.all(scales > 0):
            raise ValueError(f"scales must be 3 positive numbers, got {scales}")
        if agc_attribute is not None and not (0 < len(agc_attribute) <= 32):
            raise ValueError("agc_attribute must be 1-32 characters or None")
        self.path = Path(path)
        self.wdp_path = self.path.with_suffix(".wdp")
        self.version = version
        self.point_format = int(point_format)
        self.bits = int(bits)
        self.storage = storage
        self.agc_attribute = agc_attribute
        self.agc_extra = agc_attribute is not None and agc_attribute != "user_data"
        self.scales = scales
        self.offsets = None if offsets is None else np.asarray(offsets, dtype=np.float64)
        self.system_identifier = system_identifier
        self.generating_software = generating_software
        self.creation = (int(creation[0]), int(creation[1]))
        self.file_source_id = int(file_source_id)
        if wkt is not None and (problem := wkt_problem(wkt)):
            raise WaveforestError(f"{self.path}: wkt: {problem}")
        self.wkt = wkt
        self.gps_time_type = gps_time_type
        extra = [(agc_attribute, "<f8")] if self.agc_extra else []
        self.dtype = point_dtype(self.point_format, extra)
        self._sample_dtype = np.dtype("u1") if bits == 8 else np.dtype("<u2")
        self._max_dn = float(2**bits - 1)

        self._descriptors: dict[tuple, WavePacketDescriptor] = {}
        self._n_points = 0
        self._n_pulses = 0
        self._wave_bytes = 0
        self._by_return = np.zeros(16, dtype=np.int64)
        self._imin = np.full(3, np.iinfo(np.int64).max, dtype=np.int64)
        self._imax = np.full(3, np.iinfo(np.int64).min, dtype=np.int64)
        self._closed = False
        output_folder(self.path)
        if storage == "external":
            output_folder(self.wdp_path)
        self._points_tmp = make_temp(self.path, ".points.part")
        target = self.wdp_path if storage == "external" else self.path
        try:
            self._wave_tmp = make_temp(target, ".wave.part")
        except BaseException:
            self._points_tmp.unlink()
            raise
        self._points_fh = open(self._points_tmp, "wb")
        self._wave_fh = open(self._wave_tmp, "wb")
        if storage == "external":  # the .wdp keeps its 60-byte header at the start
            self._wave_fh.write(b"\0" * WAVEFORM_HEADER_SIZE)

    # -- context manager ---------------------------------------------------------------

    def __enter__(self) -> WaveformLasWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
            return
        self.abort()
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS):
            raise WaveforestError(f"{self.path}: cannot write the output ({exc.strerror or exc})") from exc

    def abort(self) -> None:
        """Discard everything written so far (no output file is created)."""
        self._closed = True
        for fh in (self._points_fh, self._wave_fh):
            if not fh.closed:
                fh.close()
        for tmp in (self._points_tmp, self._wave_tmp):
            if tmp.exists():
                tmp.unlink()

    @property
    def n_pulses(self) -> int:
        return self._n_pulses

    @property
    def n_points(self) -> int:
        return self._n_points

    @property
    def descriptors(self) -> list[WavePacketDescriptor]:
        return sorted(self._descriptors.values(), key=lambda d: d.index)

    # -- writing ------------------------------------------------------------------------

    def write(self, pulses: pa.Table) -> None:
        """Append the pulses of a pulse table (one packet each, one point per echo)."""
        if self._closed:
            raise ValueError(f"{self.path}: writer is closed")
        try:
            self._write(check_pulses(pulses, self.path))
        except BaseException:
            self.abort()
            raise

    def _fail(self, message: str) -> None:
        raise LasWaveformError(f"{self.path}: cannot write pulse table: {message}")

    def _write(self, t: pa.Table) -> None:
        """Check one chunk of a pulse table and append its points and packets.

        Steps: :meth:`_chunk` (columns and per-echo consistency), :meth:`_check_geometry`,
        :meth:`_check_digitizer`, :meth:`_descriptor_index`, :meth:`_point_records`; then the
        records and the raw samples are appended to the temporary files. Any violation
        raises :class:`LasWaveformError` before anything of the chunk is written.
        """
        if t.num_rows == 0:
            return
        c = self._chunk(t)
        self._check_geometry(c)
        spacing_ps = self._check_digitizer(c)
        desc_index = self._descriptor_index(c, spacing_ps)
        packet_size = (c.n_samples * self._sample_dtype.itemsize).astype(np.int64)
        base = WAVEFORM_HEADER_SIZE + self._wave_bytes  # offsets count from the record header
        packet_offset = np.where(c.has_wf, base + np.concatenate([[0], np.cumsum(packet_size)[:-1]]), 0)
        rec, q, return_number = self._point_records(c, desc_index, packet_offset, packet_size)

        self._points_fh.write(rec.tobytes())
        if c.samples.size:
            raw = c.samples.astype(self._sample_dtype).tobytes()
            self._wave_fh.write(raw)
            self._wave_bytes += len(raw)
        self._n_points += len(rec)
        self._n_pulses += c.n
        self._by_return += np.bincount(return_number, minlength=16)[:16]
        self._imin = np.minimum(self._imin, q.min(axis=0))
        self._imax = np.maximum(self._imax, q.max(axis=0))

    def _chunk(self, t: pa.Table) -> _Chunk:
        """The columns of a non-empty pulse table as arrays, with the per-pulse checks.

        Raises :class:`LasWaveformError` when the echo lists of a pulse differ in length or
        from ``n_echoes``, a pulse has no echo or more than the point format's return number
        holds, ``gps_time`` is not finite or not unique, ``dir`` is not a unit vector (within
        :data:`DIR_NORM_TOL`), or an echo position or time is not finite.
        """
        col = lambda name: t.column(name).to_numpy().astype(np.float64)  # noqa: E731
        pulse_id = t.column("pulse_id").to_numpy()
        gps = col("gps_time")
        direction = np.stack([col("dir_x"), col("dir_y"), col("dir_z")], axis=1)
        samples, s_off = _list_column(t, "samples")
        ex, e_off = _list_column(t, "echo_x")
        ey, ey_off = _list_column(t, "echo_y")
        ez, ez_off = _list_column(t, "echo_z")
        et, et_off = _list_column(t, "echo_time_ns")
        ei, ei_off = _list_column(t, "echo_intensity")
        n_echo = np.diff(e_off)
        for name, other in (("echo_y", ey_off), ("echo_z", ez_off), ("echo_time_ns", et_off), ("echo_intensity", ei_off)):
            if not np.array_equal(other, e_off):
                bad = int(np.flatnonzero(np.diff(other) != n_echo)[0])
                self._fail(f"pulse_id {pulse_id[bad]}: {name} has {np.diff(other)[bad]} values, echo_x has {n_echo[bad]}")
        declared = t.column("n_echoes").to_numpy().astype(np.int64)
        if not np.array_equal(declared, n_echo):
            bad = int(np.flatnonzero(declared != n_echo)[0])
            self._fail(f"pulse_id {pulse_id[bad]}: n_echoes = {declared[bad]} but {n_echo[bad]} echoes are listed")
        if np.any(n_echo < 1):
            bad = int(np.flatnonzero(n_echo < 1)[0])
            self._fail(f"pulse_id {pulse_id[bad]} has no DR echo (a LAS point is needed to carry its waveform)")
        max_ret = MAX_RETURNS[self.point_format]
        if np.any(n_echo > max_ret):
            bad = int(np.flatnonzero(n_echo > max_ret)[0])
            self._fail(f"pulse_id {pulse_id[bad]} has {n_echo[bad]} echoes; point format {self.point_format} stores at most {max_ret}")
        if not np.all(np.isfinite(gps)):
            self._fail("gps_time must be finite")
        if self.gps_time_type == "week" and not np.all((gps >= 0) & (gps < GPS_WEEK_S)):
            self._fail(f"gps_time {float(gps[(gps < 0) | (gps >= GPS_WEEK_S)][0])!r} is not GPS week time "
                       f"(expected [0, {GPS_WEEK_S:g}) s, or gps_time_type 'standard')")
        sorted_gps = np.sort(gps)
        if np.any(sorted_gps[1:] == sorted_gps[:-1]):
            dup = sorted_gps[1:][sorted_gps[1:] == sorted_gps[:-1]][0]
            self._fail(f"two pulses share gps_time {float(dup)!r} (a reader groups returns by gps_time)")
        norm = np.linalg.norm(direction, axis=1)
        if not np.all(np.abs(norm - 1.0) <= DIR_NORM_TOL):
            bad = int(np.flatnonzero(~(np.abs(norm - 1.0) <= DIR_NORM_TOL))[0])
            self._fail(f"pulse_id {pulse_id[bad]}: dir is not a unit vector (|dir| = {norm[bad]})")
        echo_xyz = np.stack([ex, ey, ez], axis=1).astype(np.float64)
        if not np.all(np.isfinite(echo_xyz)) or not np.all(np.isfinite(et)):
            self._fail("echo_x/_y/_z and echo_time_ns must be finite")
        n_samples = np.diff(s_off)
        pulse_of_echo = np.repeat(np.arange(t.num_rows), n_echo)
        return _Chunk(
            n=t.num_rows,
            pulse_id=pulse_id,
            gps=gps,
            direction=direction / norm[:, None],
            anchor=np.stack([col("anchor_x"), col("anchor_y"), col("anchor_z")], axis=1),
            sampling_ns=col("sampling_ns"),
            gain=col("digitizer_gain"),
            dig_offset=col("digitizer_offset"),
            scan=col("scan_angle_deg"),
            scan_flags=_optional(t, "scan_flags", np.uint8),
            source_id=_optional(t, "point_source_id", np.uint16),
            agc=col("agc"),
            samples=samples,
            s_off=s_off,
            n_samples=n_samples,
            echo_xyz=echo_xyz,
            et=et,
            ei=ei,
            e_off=e_off,
            n_echo=n_echo,
            has_wf=n_samples > 0,
            pulse_of_echo=pulse_of_echo,
            wf_echo=(n_samples > 0)[pulse_of_echo],
        )

    def _check_geometry(self, c: _Chunk) -> None:
        """Every echo of a pulse with a waveform lies on its beam (the LAS relation).

        ``|anchor + dir * echo_time_ns * RANGE_PER_NS - echo_xyz| <= GEOMETRY_TOL_M``, else
        :class:`LasWaveformError`.
        """
        if not np.any(c.wf_echo):
            return
        pe = c.pulse_of_echo[c.wf_echo]
        model = c.anchor[pe] + c.direction[pe] * (c.et[c.wf_echo] * RANGE_PER_NS)[:, None]
        miss = np.linalg.norm(model - c.echo_xyz[c.wf_echo], axis=1)
        if not np.all(miss <= GEOMETRY_TOL_M):
            k = int(np.flatnonzero(~(miss <= GEOMETRY_TOL_M))[0])
            self._fail(
                f"pulse_id {c.pulse_id[pe[k]]}: echo lies {miss[k]:.4f} m from anchor + dir * echo_time_ns * "
                f"RANGE_PER_NS (tolerance {GEOMETRY_TOL_M} m); LAS cannot store such an echo"
            )

    def _check_digitizer(self, c: _Chunk) -> np.ndarray:
        """(n,) sampling interval of each pulse in whole picoseconds (float64).

        Raises :class:`LasWaveformError` when a sample is not a whole number in
        ``[0, 2**bits - 1]`` or a waveform's ``sampling_ns * 1000`` is not a whole number of
        picoseconds in ``[1, 2**32)`` (within :data:`SPACING_TOL_PS`).
        """
        samples = c.samples
        if samples.size:
            ok = np.isfinite(samples) & (samples >= 0) & (samples <= self._max_dn) & (samples == np.round(samples))
            if not np.all(ok):
                k = int(np.flatnonzero(~ok)[0])
                p = int(np.searchsorted(c.s_off, k, side="right") - 1)
                self._fail(
                    f"pulse_id {c.pulse_id[p]}: sample value {float(samples[k])!r} is not a whole number in "
                    f"[0, {int(self._max_dn)}] ({self.bits}-bit digitizer)"
                )
        spacing = c.sampling_ns * 1000.0
        spacing_ps = np.round(spacing)
        whole = np.isfinite(spacing) & (spacing_ps >= 1) & (spacing_ps < 2**32) & (np.abs(spacing - spacing_ps) <= SPACING_TOL_PS)
        bad = c.has_wf & ~whole
        if np.any(bad):
            k = int(np.flatnonzero(bad)[0])
            self._fail(f"pulse_id {c.pulse_id[k]}: sampling_ns = {float(c.sampling_ns[k])!r} is not a whole number of picoseconds")
        return spacing_ps

    def _descriptor_index(self, c: _Chunk, spacing_ps: np.ndarray) -> np.ndarray:
        """(n,) uint8 wave packet descriptor index of each pulse (0: no waveform).

        One descriptor per distinct (samples, spacing, gain, offset), numbered in order of
        first appearance over the whole file; new ones are added to ``self._descriptors``.
        More than :data:`MAX_DESCRIPTORS` raise :class:`LasWaveformError`.
        """
        desc_index = np.zeros(c.n, dtype=np.uint8)
        if not np.any(c.has_wf):
            return desc_index
        keys = np.zeros(c.n, dtype=[("n", "<i8"), ("sp", "<i8"), ("g", "<i8"), ("o", "<i8")])
        keys["n"] = c.n_samples
        keys["sp"] = np.where(c.has_wf, spacing_ps, 0).astype(np.int64)
        keys["g"] = c.gain.view(np.int64)
        keys["o"] = c.dig_offset.view(np.int64)
        wf_rows = np.flatnonzero(c.has_wf)
        uniq, first, inverse = np.unique(keys[wf_rows], return_index=True, return_inverse=True)
        index_of_uniq = np.zeros(len(uniq), dtype=np.uint8)
        for u in np.argsort(first, kind="stable"):
            key = tuple(int(v) for v in uniq[u].tolist())
            desc = self._descriptors.get(key)
            if desc is None:
                if len(self._descriptors) >= MAX_DESCRIPTORS:
                    self._fail(f"more than {MAX_DESCRIPTORS} distinct (samples, sampling, gain, offset) packet layouts")
                row = wf_rows[first[u]]
                desc = WavePacketDescriptor(
                    index=len(self._descriptors) + 1,
                    bits=self.bits,
                    compression=0,
                    n_samples=int(c.n_samples[row]),
                    spacing_ps=int(spacing_ps[row]),
                    gain=float(c.gain[row]),
                    offset=float(c.dig_offset[row]),
                )
                self._descriptors[key] = desc
            index_of_uniq[u] = desc.index
        desc_index[wf_rows] = index_of_uniq[inverse.ravel()]
        return desc_index

    def _point_records(
        self, c: _Chunk, desc_index: np.ndarray, packet_offset: np.ndarray, packet_size: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The chunk's LAS point records, one per echo (the mapping of the module docstring).

        Returns ``(records, q, return_number)``: (m,) records of ``self.dtype``, (m, 3) int64
        quantised coordinates and (m,) return numbers (1-based). Sets ``self.offsets`` from
        the first chunk when none was given. Coordinates that do not fit int32 under the
        header scales and offsets raise :class:`LasWaveformError`.
        """
        if self.offsets is None:
            self.offsets = np.floor(c.echo_xyz.min(axis=0) / 1000.0) * 1000.0
        q = np.round((c.echo_xyz - self.offsets) / self.scales)
        if np.any(q < np.iinfo(np.int32).min) or np.any(q > np.iinfo(np.int32).max):
            self._fail(f"echo coordinates do not fit the header scales {self.scales} and offsets {self.offsets}")
        q = q.astype(np.int64)
        pulse_of_echo = c.pulse_of_echo
        m = len(pulse_of_echo)
        return_number = np.arange(m) - np.repeat(c.e_off[:-1], c.n_echo) + 1
        rec = np.zeros(m, dtype=self.dtype)
        rec["X"], rec["Y"], rec["Z"] = q[:, 0], q[:, 1], q[:, 2]
        inten = np.nan_to_num(np.round(c.ei.astype(np.float64)), nan=0.0)
        rec["intensity"] = np.clip(inten, 0, 65535).astype(np.uint16)
        flags = c.scan_flags[pulse_of_echo]
        rec["bit_fields"] = pack_return_bits(self.point_format, return_number, c.n_echo[pulse_of_echo], flags)
        if self.point_format in (9, 10):
            rec["classification_flags"] = pack_scan_bits(flags)
        scan_deg = np.nan_to_num(c.scan, nan=0.0)
        if self.point_format in (4, 5):
            rec["scan_angle_rank"] = np.clip(np.round(scan_deg), -90, 90).astype(np.int8)[pulse_of_echo]
        else:
            units = np.clip(np.round(scan_deg / SCAN_ANGLE_UNIT_DEG), -30000, 30000).astype(np.int16)
            rec["scan_angle"] = units[pulse_of_echo]
        if self.agc_attribute == "user_data":
            rec["user_data"] = np.clip(np.nan_to_num(np.round(c.agc), nan=0.0), 0, 255).astype(np.uint8)[pulse_of_echo]
        elif self.agc_extra:
            rec[self.agc_attribute] = c.agc[pulse_of_echo]
        rec["gps_time"] = c.gps[pulse_of_echo]
        rec["point_source_id"] = c.source_id[pulse_of_echo]
        rec["wavepacket_index"] = desc_index[pulse_of_echo]
        rec["wavepacket_offset"] = packet_offset[pulse_of_echo]
        rec["wavepacket_size"] = np.where(c.has_wf, packet_size, 0)[pulse_of_echo]
        rec["return_point_wave_location"] = np.where(c.wf_echo, c.et * 1000.0, 0.0).astype(np.float32)
        dt = (-c.direction * (RANGE_PER_NS / 1000.0)).astype(np.float32)
        rec["x_t"], rec["y_t"], rec["z_t"] = dt[pulse_of_echo, 0], dt[pulse_of_echo, 1], dt[pulse_of_echo, 2]
        return rec, q, return_number

    # -- closing ------------------------------------------------------------------------

    def _vlrs(self) -> tuple[bytes, int]:
        out, count = [], 0
        if self.agc_extra:
            eb = np.zeros((), EXTRA_BYTES_DESCRIPTOR)
            eb["data_type"] = EXTRA_BYTES_FLOAT64
            eb["name"] = text_field(self.agc_attribute, 32)
            eb["description"] = text_field("AGC value of the pulse", 32)
            out.append(_vlr(LASF_SPEC, EXTRA_BYTES_RECORD_ID, eb.tobytes(), "Extra bytes"))
            count += 1
        for d in self.descriptors:
            out.append(_vlr(LASF_SPEC, WPD_INDEX_OFFSET + d.index, d.body(), f"Waveform packet descriptor {d.index}"))
            count += 1
        if self.wkt is not None:
            out.append(_vlr(LASF_PROJECTION, WKT_RECORD_ID, self.wkt.encode("ascii") + b"\0", "OGC WKT"))
            count += 1
            if self.version == "1.3":  # 1.3 readers know GeoTIFF keys only
                directory, ascii_params = geokeys(self.wkt)
                out.append(_vlr(LASF_PROJECTION, GEOKEY_DIRECTORY_RECORD_ID, directory, "GeoTIFF GeoKeyDirectoryTag"))
                out.append(_vlr(LASF_PROJECTION, GEOASCII_PARAMS_RECORD_ID, ascii_params, "GeoTIFF GeoAsciiParamsTag"))
                count += 2
        return b"".join(out), count

    def _header(self, vlr_bytes: int, n_vlrs: int) -> bytes:
        is14 = self.version == "1.4"
        dt = HEADER_14 if is14 else HEADER_13
        h = np.zeros((), dt)
        h["signature"] = LAS_SIGNATURE
        h["file_source_id"] = self.file_source_id
        ge = GE_WAVEFORM_INTERNAL if self.storage == "internal" else GE_WAVEFORM_EXTERNAL
        if self.gps_time_type == "standard":
            ge |= GE_GPS_STANDARD
        if is14 and (self.point_format >= 6 or self.wkt is not None):
            ge |= GE_WKT
        h["global_encoding"] = ge
        h["version_major"] = 1
        h["version_minor"] = int(self.version[2])
        h["system_identifier"] = text_field(self.system_identifier, 32)
        h["generating_software"] = text_field(self.generating_software, 32)
        h["creation_day"], h["creation_year"] = self.creation
        h["header_size"] = dt.itemsize
        offset_to_points = dt.itemsize + vlr_bytes
        h["offset_to_point_data"] = offset_to_points
        h["number_of_vlrs"] = n_vlrs
        h["point_format"] = self.point_format
        h["point_record_length"] = self.dtype.itemsize
        n = self._n_points
        by_return = self._by_return[1:16]
        legacy_ok = self.point_format < 6 and n < 2**32
        if not is14 and not legacy_ok:
            raise LasWaveformError(f"{self.path}: LAS 1.3 cannot hold {n} points")
        if legacy_ok:
            h["legacy_point_count"] = n
            if np.all(by_return[5:] == 0):
                h["legacy_points_by_return"] = by_return[:5]
        offsets = self.offsets if self.offsets is not None else np.zeros(3)
        h["scale"] = self.scales
        h["offset"] = offsets
        if n:
            lo = self._imin * self.scales + offsets
            hi = self._imax * self.scales + offsets
            h["min_x"], h["min_y"], h["min_z"] = lo
            h["max_x"], h["max_y"], h["max_z"] = hi
        end_of_points = offset_to_points + n * self.dtype.itemsize
        if self.storage == "internal":
            h["start_of_waveform_data"] = end_of_points
        if is14:
            if self.storage == "internal":
                h["start_of_first_evlr"] = end_of_points
                h["number_of_evlrs"] = 1
            h["point_count"] = n
            h["points_by_return"] = by_return
        return h.tobytes()

    def close(self) -> Path:
        """Assemble the file(s) and move them onto their final names; return the LAS path."""
        if self._closed:
            return self.path
        try:
            self._points_fh.close()
            self._wave_fh.close()
            vlr_bytes, n_vlrs = self._vlrs()
            header = self._header(len(vlr_bytes), n_vlrs)
            las_tmp = make_temp(self.path, ".part")
            try:
                with open(las_tmp, "wb") as out:
                    out.write(header)
                    out.write(vlr_bytes)
                    with open(self._points_tmp, "rb") as src:
                        shutil.copyfileobj(src, out, COPY_BUFFER_BYTES)
                    if self.storage == "internal":
                        out.write(_waveform_record_header(self._wave_bytes))
                        with open(self._wave_tmp, "rb") as src:
                            shutil.copyfileobj(src, out, COPY_BUFFER_BYTES)
                if self.storage == "external":
                    with open(self._wave_tmp, "r+b") as fh:
                        fh.write(_waveform_record_header(self._wave_bytes))
                    publish(self._wave_tmp, self.wdp_path)
                publish(las_tmp, self.path)
            except OSError as exc:
                raise WaveforestError(f"{self.path}: cannot write the output ({exc.strerror or exc})") from exc
            finally:
                if las_tmp.exists():
                    las_tmp.unlink()
        finally:
            self.abort()  # removes whatever temporary file is left
        return self.path


def write_waveform_las(path: str | os.PathLike, pulses: pa.Table | list[pa.Table], **options) -> Path:
    """Write a pulse table (or a list of chunks) as a LAS waveform file.

    ``options`` are those of :class:`WaveformLasWriter` (``version``, ``point_format``,
    ``bits``, ``storage``, ``agc_attribute``, ``scales``, ``offsets``, ...).
    Returns the path of the LAS file.
    """
    chunks = pulses if isinstance(pulses, (list, tuple)) else [pulses]
    with WaveformLasWriter(path, **options) as writer:
        for chunk in chunks:
            writer.write(chunk)
    return writer.path
