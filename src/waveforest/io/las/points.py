"""LAS point records -> compact records, checked, and grouped into pulses by GPS time.

:class:`PointScanner` streams the points of a :class:`waveforest.io.las.file.LasWaveformFile` with laspy
in chunks and keeps :data:`COMPACT_DTYPE` records (76 bytes a point), checking every
waveform reference on the way (descriptor defined, not empty, uncompressed, finite gain
and offset, consistent with the packet size, packet inside the waveform data).
:func:`sort_points` groups records into pulses without copying them.

Corrupt single records are dropped, counted and reported (a warning when the scan ends,
and the counts in :class:`PointScanner`), rather than stopping a whole flight line:

- a point with a non-finite GPS time is dropped: it cannot be grouped into a pulse nor
  placed on a trajectory, and NaN GPS times would each make a pulse of their own;
- a point whose beam geometry is unusable (x(t), y(t), z(t) all 0 or not finite, or a
  non-finite return point waveform location) keeps its XYZ as an echo, but loses its
  waveform packet: the packet cannot be placed in space. A pulse left with no packet is
  then skipped and counted as one "without waveform".

File-wide defects (a descriptor that contradicts the packet sizes, a packet outside the
waveform data) are errors: every pulse would be wrong, and the file needs repair.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from waveforest.io.las.file import LasWaveformFile, fail, open_point_reader
from waveforest.io.las.format import SCAN_ANGLE_UNIT_DEG, SUPPORTED_COMPRESSION, LasWaveformError, warn

COMPACT_DTYPE = np.dtype(
    [
        ("gps", "<f8"),
        ("ret", "u1"),
        ("wpi", "u1"),
        ("off", "<u8"),
        ("loc", "<f4"),
        ("d", "<f4", (3,)),
        ("xyz", "<f8", (3,)),
        ("intensity", "<f4"),
        ("scan", "<f8"),
        ("agc", "<f8"),
    ]
)
"""What the reader keeps of one LAS point (76 bytes)."""


class PointScanner:
    """Reads the points of a file in chunks into :data:`COMPACT_DTYPE` records and checks them."""

    def __init__(self, las: LasWaveformFile, agc_dimension: str | None, chunk_points: int):
        self.las = las
        self.agc_dimension = agc_dimension
        self.chunk_points = int(chunk_points)
        self.lut = las.descriptor_tables()
        defined = np.zeros(256, bool)
        empty = np.zeros(256, bool)
        comp = np.zeros(256, np.int64)
        bits = np.zeros(256, np.int64)
        for i, d in las.descriptors.items():
            defined[i] = True
            empty[i] = d.empty
            comp[i] = d.compression
            bits[i] = d.bits
        self.defined, self.empty, self.comp, self.bits = defined, empty, comp, bits
        self.packet_bytes = self.lut["n_samples"] * self.lut["sample_bytes"]
        self._warned_size = False
        self.n_read = 0
        """Point records read by the last full scan (``chunks("all")``)."""
        self.n_bad_gps = 0
        """Points dropped by the last full scan for a non-finite GPS time."""
        self.n_bad_geometry = 0
        """Points of the last full scan whose waveform packet was dropped (unusable beam geometry)."""

    def chunks(self, fields: str = "all") -> Iterator[np.ndarray]:
        """Yield compact records (``fields="all"``) or (gps, agc) pairs (``fields="keys"``).

        Points with a non-finite GPS time are left out of both; a full scan counts them
        (and the points that lose their packet) and warns once at its end.
        """
        las = self.las
        try:
            reader = open_point_reader(las)
        except Exception as exc:
            raise fail(las.path, f"cannot open the point records ({type(exc).__name__}: {exc})") from exc
        if fields == "all":
            self.n_read = self.n_bad_gps = self.n_bad_geometry = 0
        with reader:
            reader.header.point_count = las.n_points  # legacy/64-bit count resolved in open_waveform_las
            start = 0
            try:
                iterator = reader.chunk_iterator(self.chunk_points)
                for pts in iterator:
                    n = len(pts)
                    if fields == "keys":
                        gps = np.asarray(pts.array["gps_time"], dtype=np.float64)
                        ok = np.isfinite(gps)
                        agc = self._agc(pts, n)
                        yield (gps, agc) if ok.all() else (gps[ok], agc[ok])
                    else:
                        yield self._compact(pts, start)
                    start += n
            except LasWaveformError:
                raise
            except Exception as exc:
                raise fail(las.path, f"cannot read point records near point {start} ({type(exc).__name__}: {exc})") from exc
            if start != las.n_points:
                raise fail(las.path, f"truncated file: read {start} of the {las.n_points} points the header announces")
        if fields == "all":
            self.n_read = start
            self._report_drops()

    def _report_drops(self) -> None:
        path = self.las.path
        if self.n_bad_gps:
            warn(f"{path}: {self.n_bad_gps} point(s) with a non-finite GPS time dropped (they cannot be grouped into pulses)")
        if self.n_bad_geometry:
            warn(
                f"{path}: {self.n_bad_geometry} point(s) with an unusable beam geometry (x(t), y(t), z(t) all 0 or not "
                "finite, or a non-finite return point waveform location) kept without their waveform packet"
            )

    def _agc(self, pts, n: int) -> np.ndarray:
        if self.agc_dimension is None:
            return np.full(n, np.nan)
        values = np.asarray(pts[self.agc_dimension], dtype=np.float64)
        return values if values.ndim == 1 else values.reshape(n, -1)[:, 0]  # array dimension: first element

    def _compact(self, pts, start: int) -> np.ndarray:
        las, arr = self.las, pts.array
        n = len(arr)
        wpi = arr["wavepacket_index"].astype(np.int64)
        off = arr["wavepacket_offset"].astype(np.uint64)
        size = arr["wavepacket_size"].astype(np.int64)
        loc = arr["return_point_wave_location"]
        d = np.stack([arr["x_t"], arr["y_t"], arr["z_t"]], axis=1)
        gps_ok = np.isfinite(arr["gps_time"])
        bad_geometry = gps_ok & (wpi > 0) & ~(np.isfinite(loc) & np.all(np.isfinite(d), axis=1) & np.any(d != 0, axis=1))
        wpi[bad_geometry] = 0
        self.n_bad_gps += int(n - np.count_nonzero(gps_ok))
        self.n_bad_geometry += int(np.count_nonzero(bad_geometry))
        used = wpi > 0
        self._check_packets(start, wpi, off, size, used & gps_ok)
        rec = np.empty(n, COMPACT_DTYPE)
        rec["gps"] = arr["gps_time"]
        rec["ret"] = np.asarray(pts.return_number, dtype=np.uint8)
        rec["wpi"] = wpi
        rec["off"] = off
        rec["loc"] = loc
        rec["d"] = d
        for k, name in enumerate("XYZ"):
            rec["xyz"][:, k] = arr[name] * las.scales[k] + las.offsets[k]
        rec["intensity"] = arr["intensity"]
        if las.point_format in (4, 5):
            rec["scan"] = arr["scan_angle_rank"]
        else:
            rec["scan"] = arr["scan_angle"] * SCAN_ANGLE_UNIT_DEG
        rec["agc"] = self._agc(pts, n)
        return rec if gps_ok.all() else rec[gps_ok]

    def _check_packets(self, start: int, wpi, off, size, used) -> None:
        las, path = self.las, self.las.path
        if not np.any(used):
            return

        def first(mask) -> int:
            return int(np.flatnonzero(mask)[0])

        bad = used & ~self.defined[wpi]
        if np.any(bad):
            k = first(bad)
            known = ", ".join(str(i) for i in las.descriptors) or "none"
            raise fail(
                path,
                f"point {start + k} uses wave packet descriptor index {wpi[k]}, which the file does not define "
                f"(defined: {known}); descriptor index out of range",
            )
        bad = used & self.empty[wpi]
        if np.any(bad):
            k = first(bad)
            d = las.descriptors[int(wpi[k])]
            raise fail(
                path,
                f"point {start + k} uses wave packet descriptor {wpi[k]}, which describes no waveform "
                f"({d.n_samples} samples, {d.spacing_ps} ps spacing)",
            )
        bad = used & ~np.isin(self.comp[wpi], SUPPORTED_COMPRESSION)
        if np.any(bad):
            k = first(bad)
            raise fail(
                path,
                f"wave packet descriptor {wpi[k]} uses waveform compression type {self.comp[wpi[k]]}; "
                "only uncompressed packets (type 0) are supported",
            )
        bad = used & (self.lut["sample_bytes"][wpi] == 0)
        if np.any(bad):
            k = first(bad)
            raise fail(path, f"wave packet descriptor {wpi[k]} has {self.bits[wpi[k]]} bits per sample; 1-16 or 25-32 supported")
        bad = used & ~(np.isfinite(self.lut["gain"][wpi]) & np.isfinite(self.lut["offset"][wpi]))
        if np.any(bad):
            k = first(bad)
            d = las.descriptors[int(wpi[k])]
            raise fail(path, f"wave packet descriptor {wpi[k]} has digitizer gain {d.gain} and offset {d.offset}; finite numbers expected")
        need = self.packet_bytes[wpi]
        # a packet size that is a whole number of samples of another width: the descriptor's
        # bits per sample contradict the packets (e.g. 8-bit descriptor, 16-bit packets);
        # decoding them with the descriptor would give garbage samples
        ns = np.maximum(self.lut["n_samples"][wpi], 1)
        width = size // ns
        bad = used & (size != need) & (size % ns == 0) & np.isin(width, (1, 2, 4))
        if np.any(bad):
            k = first(bad)
            raise fail(
                path,
                f"point {start + k}: wave packet descriptor {wpi[k]} says {self.bits[wpi[k]]} bits per sample "
                f"({ns[k]} samples = {need[k]} bytes), but the point's packet size is {size[k]} bytes, i.e. "
                f"{width[k] * 8}-bit samples; the descriptor does not match the packets",
            )
        bad = used & (size < need)
        if np.any(bad):
            k = first(bad)
            raise fail(path, f"point {start + k}: packet size {size[k]} bytes is smaller than descriptor {wpi[k]} needs ({need[k]} bytes)")
        if not self._warned_size and np.any(used & (size > need)):
            k = first(used & (size > need))
            warn(f"{path}: point {start + k}: packet size {size[k]} bytes exceeds descriptor {wpi[k]} ({need[k]} bytes); reading the descriptor's samples")
            self._warned_size = True
        end = off.astype(np.float64) + need  # float: u64 offsets from broken files may overflow int64
        bad = used & (end > las.waveform.size)
        if np.any(bad):
            k = first(bad)
            wf = las.waveform
            where = f"{wf.path.name} ({wf.size} bytes)" if wf.storage == "external" else f"the waveform record ({wf.size} bytes from byte {wf.base})"
            raise fail(
                path,
                f"point {start + k}: waveform packet at byte offset {off[k]} ({need[k]} bytes) lies beyond the end of "
                f"{where}; the {'.wdp file is short' if wf.storage == 'external' else 'file is truncated'}",
            )


@dataclass(frozen=True)
class PulseIndex:
    """Points of a bucket grouped into pulses (or packets of pulses), without copying them.

    Attributes
    ----------
    order : (n,) int64
        Point indices sorted by GPS time, then (packets) descriptor and offset, return number.
    starts : (n_groups + 1,) int64
        Group ``j`` is ``rec[order[starts[j]:starts[j + 1]]]``.
    chosen : (n_groups,) int64
        Position in ``order`` of the group's first return with a waveform, ``n`` if none.
    pulse : (n_groups,) int64
        The pulse of each group, numbered from 0 within the bucket in GPS-time order (a pulse
        is one group, or several groups when grouped by packet).
    """

    order: np.ndarray
    starts: np.ndarray
    chosen: np.ndarray
    pulse: np.ndarray

    @property
    def n_pulses(self) -> int:
        """Groups in the index (pulses, or packets of pulses)."""
        return len(self.chosen)


def sort_points(rec: np.ndarray, by_packet: bool = False) -> PulseIndex:
    """Group compact point records (:data:`COMPACT_DTYPE`) into pulses by GPS time; with
    ``by_packet``, into the waveform packets of each pulse (points without a packet dropped,
    a pulse without any packet kept as one group without a waveform)."""
    n = len(rec)
    if by_packet:
        order = np.lexsort((rec["ret"], rec["off"], rec["wpi"], rec["gps"]))
    else:
        order = np.lexsort((rec["off"], rec["ret"], rec["gps"]))
    gps = rec["gps"][order]
    new_pulse = np.ones(n, dtype=bool)
    new_pulse[1:] = gps[1:] != gps[:-1]
    del gps
    if by_packet and n:
        pid = np.cumsum(new_pulse) - 1
        has = rec["wpi"][order] > 0
        keep = has | ~np.maximum.reduceat(has, np.flatnonzero(new_pulse))[pid]  # a pulse without packets: one group
        order, pid = order[keep], pid[keep]
        n = len(order)
        wpi, off = rec["wpi"][order], rec["off"][order]
        new_pulse = np.ones(n, dtype=bool)
        new_pulse[1:] = pid[1:] != pid[:-1]
        new = new_pulse.copy()
        new[1:] |= (wpi[1:] != wpi[:-1]) | (off[1:] != off[:-1])
    else:
        new = new_pulse
    starts = np.append(np.flatnonzero(new), n).astype(np.int64)
    if n == 0:
        return PulseIndex(order, starts, np.zeros(0, np.int64), np.zeros(0, np.int64))
    pulse = (np.cumsum(new_pulse) - 1)[starts[:-1]]
    pos = np.where(rec["wpi"][order] > 0, np.arange(n), n)
    return PulseIndex(order, starts, np.minimum.reduceat(pos, starts[:-1]), pulse)
