"""Read LAS 1.3/1.4 waveform files (point formats 4, 5, 9, 10) into pulse tables.

:class:`WaveformPulseReader` streams a file checked by :func:`waveforest.io.las.file.open_waveform_las`
as pulse tables (:data:`waveforest.io.pulses.PULSE_SCHEMA`); :func:`read_waveform_las` reads it whole.

Pulses
------
The returns of one pulse share a GPS time; a pulse row groups every point of one
``gps_time`` (points may come in any order in the file). Some writers cut a long waveform
into several packets, so the returns of one pulse may sit in different packets; the pulse
then takes the packet of its first return (the lowest return number that has a waveform)
and keeps *all* its returns as DR echoes, in return order. Echo times are from the first
sample of that packet: ``L / 1000`` ns for returns in the same packet, and for returns in
another packet the projection ``(P - anchor) . dir / RANGE_PER_NS`` (which may lie beyond
the end of the record). Pulses none of whose returns has a waveform (descriptor index 0)
are skipped with a warning. ``pulse_id`` is the index of the pulse in GPS-time order
(skipped pulses keep their number, so ids are stable).

Geometry (LAS 1.4 R15, see :mod:`waveforest.io.las.format`): for the chosen return ``P`` with location
``L`` (ps) and ``d = (x(t), y(t), z(t))`` (m/ps, target -> sensor), the first sample lies at
``anchor = P + L * d`` and ``dir = -d / |d|``. ``sampling_ns`` is the descriptor's spacing
/ 1000; samples are the raw digitizer values as float32 (DN; the descriptor's gain and
offset go to ``digitizer_gain``/``digitizer_offset`` and are not applied).

AGC: the value of the pulse's first return of a point dimension or extra-bytes dimension
(default ``user_data``). A missing dimension, or one that is 0 for every point (what files
without AGC hold in ``user_data``), gives NaN with a warning: downstream AGC normalisation
is then skipped, never faked.

Memory
------
Memory stays bounded whatever the file size. Points are read in chunks with laspy and
reduced to a 76-byte record each. A file of at most ``bucket_points`` points is sorted
in memory; a larger file is first scanned for its GPS times (keeping a sorted sample of
one in ``QUANTILE_STRIDE``), and then read in GPS-time buckets of about ``bucket_points``
points each (all returns of a pulse fall into one bucket), processed bucket by bucket. If
the points are in GPS-time order, as ALS files are written, a bucket is a run of consecutive
points cut between two GPS times; otherwise the buckets are bounded by quantiles of the GPS
times and spilled to temporary files beside the output. Waveform bytes are read through
a memory map of the ``.wdp`` file or of the LAS file's waveform record, one batch of
``batch_pulses`` pulses at a time, and the batch's pages are released after use.
"""

from __future__ import annotations

import math
import mmap
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from waveforest.constants import RANGE_PER_NS
from waveforest.errors import WaveforestError
from waveforest.io.las.file import LasWaveformFile, open_waveform_las, resolve_attribute
from waveforest.io.las.format import warn
from waveforest.io.las.gather import gather_samples
from waveforest.io.las.points import COMPACT_DTYPE, PointScanner, PulseIndex, sort_points
from waveforest.io.pulses import PULSE_SCHEMA

DEFAULT_CHUNK_POINTS = 250_000
"""Points read from the LAS file per laspy chunk."""
DEFAULT_BUCKET_POINTS = 250_000
"""Points grouped in memory at once (76 bytes each, plus an 8-byte sort index)."""
DEFAULT_BATCH_PULSES = 16_384
"""Pulses per output batch (one waveform gather, one Arrow table)."""
QUANTILE_STRIDE = 256
"""One in this many sorted GPS times of each chunk is kept to place bucket boundaries."""
_MADV_DONTNEED = getattr(mmap, "MADV_DONTNEED", None)
_RECORD_BYTES = np.dtype((np.void, COMPACT_DTYPE.itemsize))
"""A compact record as opaque bytes, for whole-record copies (NumPy copies structured records
field by field)."""


@dataclass
class ReadStats:
    """What a reader has seen so far."""

    n_points: int = 0
    n_pulses: int = 0
    n_written: int = 0
    n_without_waveform: int = 0
    n_bad_gps: int = 0
    n_bad_geometry: int = 0
    n_split_pulses: int = 0
    agc_dimension: str | None = None
    n_buckets: int = 0
    spilled: bool = False


Locator = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""``locate(gps_time (n,), first_echo (n, 3), dir (n, 3)) -> (sensor (n, 3), range_m (n,))``."""


def no_sensor(gps: np.ndarray, first_echo: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The default locator: the sensor position and range are unknown (NaN)."""
    n = len(gps)
    return np.full((n, 3), np.nan), np.full(n, np.nan)


class WaveformPulseReader:
    """Stream a LAS waveform file as pulse tables; iterate to get ``pa.Table`` batches.

    Parameters
    ----------
    path : str or Path
        LAS 1.3/1.4 file with waveform packets (a ``.wdp`` beside it when external).
    dataset : str, optional
        Value of the ``dataset`` column (default: the file stem).
    agc_attribute : str or None
        Point dimension or extra-bytes dimension holding the AGC (default ``user_data``).
    locate : callable, optional
        Sensor position and range per pulse (:data:`Locator`); default NaN.
    chunk_points, bucket_points, batch_pulses : int
        Points per laspy read, points sorted in memory at once, pulses per output table.
    tmp_dir : str or Path, optional
        Folder for spilled buckets of large files whose points are not in GPS-time order
        (default: the system temp folder).
    on_points : callable, optional
        Called with the number of points processed after each step (progress bars).
    packets : bool
        Add the chosen packet of each pulse as three columns beyond the pulse schema:
        ``wave_packet_index`` (uint8, the descriptor), ``wave_packet_offset`` (uint64, bytes
        from the start of the waveform data record) and ``wave_packet_bytes`` (uint32,
        samples x bytes per sample of the descriptor).
    by_packet : bool
        One row per waveform packet of a pulse instead of one per pulse: a pulse whose returns
        lie in several packets (RIEGL's segments) gives several rows with its ``pulse_id`` and
        GPS time, each with its packet's samples, anchor and returns; returns without a packet
        are left out. ``stats.n_split_pulses`` counts those pulses either way.

    Attributes
    ----------
    las : LasWaveformFile
    stats : ReadStats
        Filled while iterating.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        dataset: str | None = None,
        agc_attribute: str | None = "user_data",
        locate: Locator | None = None,
        chunk_points: int = DEFAULT_CHUNK_POINTS,
        bucket_points: int = DEFAULT_BUCKET_POINTS,
        batch_pulses: int = DEFAULT_BATCH_PULSES,
        tmp_dir: str | os.PathLike | None = None,
        on_points: Callable[[int], None] | None = None,
        packets: bool = False,
        by_packet: bool = False,
    ) -> None:
        for name, value in (("chunk_points", chunk_points), ("bucket_points", bucket_points), ("batch_pulses", batch_pulses)):
            if int(value) < 1:
                raise ValueError(f"{name} must be >= 1, got {value}")
        self.las: LasWaveformFile = open_waveform_las(path)
        self.dataset = dataset if dataset is not None else self.las.path.stem
        self.agc_attribute = agc_attribute
        self.locate = locate or no_sensor
        self.chunk_points = int(chunk_points)
        self.bucket_points = int(bucket_points)
        self.batch_pulses = int(batch_pulses)
        self.tmp_dir = Path(tmp_dir) if tmp_dir is not None else None
        self.on_points = on_points or (lambda n: None)
        self.packets = bool(packets)
        self.by_packet = bool(by_packet)
        self.stats = ReadStats()
        self.n_passes = 1 if self.las.n_points <= self.bucket_points else 2
        """Passes over the point records (progress total = n_passes * n_points)."""

    # buckets ------------------------------------------------------------------------

    def _agc_dimension(self) -> str | None:
        dim = resolve_attribute(self.las, self.agc_attribute)
        if self.agc_attribute and dim is None:
            warn(
                f"{self.las.path}: no point attribute {self.agc_attribute!r} (dimensions: "
                f"{', '.join(self.las.dimension_names)}); AGC set to NaN, AGC normalisation will be skipped"
            )
        return dim

    def _no_agc_values(self, dim: str) -> None:
        warn(
            f"{self.las.path}: attribute {dim!r} is 0 for every point, i.e. the file holds no AGC; "
            "AGC set to NaN, AGC normalisation will be skipped"
        )

    def buckets(self) -> Iterator[np.ndarray]:
        """Yield the compact point records in GPS-time buckets (all returns of a pulse in one)."""
        dim = self._agc_dimension()
        scanner = PointScanner(self.las, dim, self.chunk_points)
        self.stats.agc_dimension = dim
        n = self.las.n_points
        if self.n_passes == 1:
            box = [np.empty(n, COMPACT_DTYPE)]  # handed out with pop(): no reference stays here
            rec, filled, part = box[0], 0, None
            for part in scanner.chunks():
                rec.view(_RECORD_BYTES)[filled : filled + len(part)] = part.view(_RECORD_BYTES)
                filled += len(part)
                self.on_points(len(part))
            if filled < n:  # points with a non-finite GPS time were dropped
                box[0] = rec = rec[:filled]
            if dim is not None and filled and not np.any(rec["agc"] != 0):
                self._no_agc_values(dim)
                rec["agc"] = np.nan
                self.stats.agc_dimension = None
            self._scanned(scanner)
            self.stats.n_buckets = 1
            del rec, part
            yield box.pop()
            return

        # pass 1: GPS-time quantiles, whether the points are in time order, whether the AGC
        # is ever non-zero
        samples, any_agc, in_order, last = [], False, True, -np.inf
        for gps, agc in scanner.chunks("keys"):
            if in_order and len(gps):
                in_order = bool(gps[0] >= last and np.all(gps[1:] >= gps[:-1]))
                last = gps[-1]
            s = gps if in_order else np.sort(gps)
            samples.append((s[QUANTILE_STRIDE // 2 :: QUANTILE_STRIDE] if len(s) > QUANTILE_STRIDE else s).copy())
            any_agc = any_agc or (dim is not None and bool(np.any(agc != 0)))
            self.on_points(len(gps))
        if dim is not None and not any_agc:
            self._no_agc_values(dim)
            scanner.agc_dimension = None
            self.stats.agc_dimension = None
        if in_order:
            yield from self._ordered_buckets(scanner)
            return
        sample = np.sort(np.concatenate(samples))
        del samples
        n_buckets = max(1, math.ceil(n / self.bucket_points))
        ranks = (np.arange(1, n_buckets) * len(sample)) // n_buckets
        bounds = np.unique(sample[ranks])
        n_buckets = len(bounds) + 1
        self.stats.n_buckets = n_buckets

        # pass 2: spill each bucket's records to its own file
        self.stats.spilled = True
        try:
            tmp = Path(tempfile.mkdtemp(prefix=".waveforest-ingest-", dir=self.tmp_dir))
        except OSError as exc:
            raise WaveforestError(f"cannot create a folder for spilled points in {self.tmp_dir} ({exc.strerror or exc})") from exc
        try:
            files = [tmp / f"bucket{i:05d}.bin" for i in range(n_buckets)]
            for part in scanner.chunks():
                b = np.searchsorted(bounds, part["gps"], side="right")
                order = np.argsort(b, kind="stable")
                edges = np.searchsorted(b[order], np.arange(n_buckets + 1))
                part = np.take(part, order)
                for i in np.flatnonzero(np.diff(edges)):
                    with open(files[i], "ab") as fh:
                        fh.write(part[edges[i] : edges[i + 1]].tobytes())
                self.on_points(len(part))
            self._scanned(scanner)
            del part, b, order
            for f in files:
                if f.exists():
                    box = [np.fromfile(f, dtype=COMPACT_DTYPE)]
                    f.unlink()
                    yield box.pop()
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def _ordered_buckets(self, scanner: PointScanner) -> Iterator[np.ndarray]:
        """Pass 2 for points already in GPS-time order (as ALS files are written): buckets of
        about ``bucket_points`` consecutive points, cut where the GPS time changes, so that all
        returns of a pulse stay together; nothing is spilled to disk. Chunks are copied into
        one buffer per bucket (its unused pages are never touched, so never resident)."""
        cap = self.bucket_points + self.chunk_points
        box, held = [np.empty(cap, COMPACT_DTYPE)], 0
        for part in scanner.chunks():
            self.on_points(len(part))
            if held + len(part) > len(box[0]):  # one GPS time in the whole buffer: grow it
                grown = np.empty(held + cap, COMPACT_DTYPE)
                grown.view(_RECORD_BYTES)[:held] = box[0].view(_RECORD_BYTES)[:held]
                box[0] = grown
            box[0].view(_RECORD_BYTES)[held : held + len(part)] = part.view(_RECORD_BYTES)
            held += len(part)
            del part
            if held < self.bucket_points:
                continue
            gps = box[0]["gps"][:held]
            cut = int(np.searchsorted(gps, gps[-1], side="left"))  # the last time's first point
            del gps
            if cut == 0:
                continue
            nxt = np.empty(cap, COMPACT_DTYPE)
            nxt.view(_RECORD_BYTES)[: held - cut] = box[0].view(_RECORD_BYTES)[cut:held]
            box, held = [box[0][:cut], nxt], held - cut
            self.stats.n_buckets += 1
            yield box.pop(0)  # handed out: no reference stays here
        self._scanned(scanner)
        if held:
            self.stats.n_buckets += 1
            box[0] = box[0][:held]
            yield box.pop()

    def _scanned(self, scanner: PointScanner) -> None:
        """Copy the counts of a finished full scan into :attr:`stats`."""
        self.stats.n_points = scanner.n_read
        self.stats.n_bad_gps = scanner.n_bad_gps
        self.stats.n_bad_geometry = scanner.n_bad_geometry

    # pulses ---------------------------------------------------------------------------

    def __iter__(self) -> Iterator[pa.Table]:
        wf = self.las.waveform
        lut = self.las.descriptor_tables()
        next_id = 0
        with open(wf.path, "rb") as fh:
            mm, buf = None, np.zeros(0, np.uint8)
            if wf.size > 0:
                # map from the page holding `base` (mmap offsets must be page aligned)
                page_base = wf.base - wf.base % mmap.ALLOCATIONGRANULARITY
                mm = mmap.mmap(fh.fileno(), wf.base - page_base + wf.size, access=mmap.ACCESS_READ, offset=page_base)
                buf = np.frombuffer(mm, dtype=np.uint8)[wf.base - page_base :]
            try:
                for rec in self.buckets():
                    index = sort_points(rec, self.by_packet)
                    n_pulses = int(index.pulse[-1]) + 1 if len(index.pulse) else 0
                    if self.by_packet:
                        self.stats.n_split_pulses += int(np.count_nonzero(np.bincount(index.pulse) > 1))
                    p0 = 0
                    while p0 < index.n_pulses:  # batches end between pulses
                        p1 = min(index.n_pulses, p0 + self.batch_pulses)
                        p1 = int(np.searchsorted(index.pulse, index.pulse[p1 - 1], side="right"))
                        table = self._batch(rec, index, p0, p1, next_id, lut, buf)
                        p0 = p1
                        if mm is not None and _MADV_DONTNEED is not None:
                            mm.madvise(_MADV_DONTNEED)  # drop the batch's pages from the resident set
                        if table is not None:
                            self.stats.n_written += table.num_rows
                            yield table
                        del table
                    next_id += n_pulses
                    self.stats.n_pulses += n_pulses
                    del rec, index
            finally:
                del buf
                if mm is not None:
                    try:
                        mm.close()
                    except BufferError:  # an exception's traceback still holds a view; GC closes it
                        pass
        if self.stats.n_without_waveform:
            warn(f"{self.las.path}: {self.stats.n_without_waveform} pulse(s) without any waveform packet skipped")

    def _batch(self, rec, index: PulseIndex, p0, p1, first_id, lut, buf) -> pa.Table | None:
        starts = index.starts
        pt0, pt1 = int(starts[p0]), int(starts[p1])
        ch = index.chosen[p0:p1]
        keep = ch < len(rec)
        self.stats.n_without_waveform += int(np.count_nonzero(~keep))
        if not np.any(keep):
            return None
        ids = first_id + index.pulse[p0:p1][keep]
        r = np.take(rec, index.order[ch[keep]])  # the chosen return of each kept pulse
        n = len(r)
        d = r["d"].astype(np.float64)
        loc = r["loc"].astype(np.float64)
        anchor = r["xyz"] + loc[:, None] * d
        dnorm = np.linalg.norm(d, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            direction = -d / dnorm[:, None]

        # echoes: every return of the kept pulses, in return order
        counts = np.diff(starts[p0 : p1 + 1])
        pulse_local = np.repeat(np.arange(p1 - p0), counts)
        keep_pt = keep[pulse_local]
        pts = np.take(rec, index.order[pt0:pt1][keep_pt])
        kept_index = np.cumsum(keep) - 1
        pk = kept_index[pulse_local[keep_pt]]
        e_counts = counts[keep]
        same = (pts["off"] == r["off"][pk]) & (pts["wpi"] == r["wpi"][pk])
        self.stats.n_split_pulses += int(np.count_nonzero(np.bincount(pk[~same], minlength=n)))
        t_geo = np.einsum("ij,ij->i", pts["xyz"] - anchor[pk], direction[pk]) / RANGE_PER_NS
        echo_t = np.where(same, pts["loc"].astype(np.float64) / 1000.0, t_geo)
        e_off = np.zeros(n + 1, np.int64)
        np.cumsum(e_counts, out=e_off[1:])
        first_pt = np.take(pts, e_off[:-1])  # the first return of each pulse

        # waveform samples of the chosen packets
        wpi = r["wpi"].astype(np.int64)
        n_samples = lut["n_samples"][wpi]
        if int(n_samples.sum()) >= 2**31:  # list<float32> offsets are int32
            raise WaveforestError(f"{self.las.path}: batch_pulses={self.batch_pulses} gives more than 2**31 samples per batch; use fewer")
        samples, s_off = gather_samples(buf, r["off"].astype(np.int64), n_samples, lut["sample_bytes"][wpi])

        sensor, range_m = self.locate(r["gps"], first_pt["xyz"], direction)

        def lst(values, offsets, type_):
            return pa.ListArray.from_arrays(pa.array(offsets.astype(np.int32)), pa.array(values, type=type_))

        f64 = pa.float64()
        cols = {
            "dataset": pa.array([self.dataset]).take(pa.array(np.zeros(n, np.int32))),
            "pulse_id": pa.array(ids, pa.int64()),
            "source": pa.array(["real"]).take(pa.array(np.zeros(n, np.int32))),
            "gps_time": pa.array(r["gps"], f64),
            "sensor_x": pa.array(sensor[:, 0], f64),
            "sensor_y": pa.array(sensor[:, 1], f64),
            "sensor_z": pa.array(sensor[:, 2], f64),
            "dir_x": pa.array(direction[:, 0], f64),
            "dir_y": pa.array(direction[:, 1], f64),
            "dir_z": pa.array(direction[:, 2], f64),
            "anchor_x": pa.array(anchor[:, 0], f64),
            "anchor_y": pa.array(anchor[:, 1], f64),
            "anchor_z": pa.array(anchor[:, 2], f64),
            "range_m": pa.array(range_m, f64),
            "scan_angle_deg": pa.array(first_pt["scan"].astype(np.float64), f64),
            "agc": pa.array(first_pt["agc"], f64),
            "sampling_ns": pa.array(lut["spacing_ps"][wpi] / 1000.0, f64),
            "digitizer_gain": pa.array(lut["gain"][wpi], f64),
            "digitizer_offset": pa.array(lut["offset"][wpi], f64),
            "samples": lst(samples, s_off, pa.float32()),
            "n_echoes": pa.array(e_counts.astype(np.int16), pa.int16()),
            "echo_x": lst(pts["xyz"][:, 0].copy(), e_off, f64),
            "echo_y": lst(pts["xyz"][:, 1].copy(), e_off, f64),
            "echo_z": lst(pts["xyz"][:, 2].copy(), e_off, f64),
            "echo_time_ns": lst(echo_t, e_off, f64),
            "echo_intensity": lst(pts["intensity"].astype(np.float32), e_off, pa.float32()),
        }
        table = pa.Table.from_pydict(cols, schema=PULSE_SCHEMA)
        if self.packets:
            table = table.append_column("wave_packet_index", pa.array(r["wpi"], pa.uint8()))
            table = table.append_column("wave_packet_offset", pa.array(r["off"], pa.uint64()))
            table = table.append_column("wave_packet_bytes",
                                        pa.array(n_samples * lut["sample_bytes"][wpi], pa.uint32()))
        return table


def read_waveform_las(path: str | os.PathLike, **options) -> pa.Table:
    """Read a whole LAS waveform file into one pulse table (for small files and tests).

    ``options`` are those of :class:`WaveformPulseReader`.
    """
    reader = WaveformPulseReader(path, **options)
    tables = list(reader)
    if not tables:
        return PULSE_SCHEMA.empty_table()
    return pa.concat_tables(tables)


def with_rate(batches: Iterator[pa.Table], bar) -> Iterator[pa.Table]:
    """Pass pulse tables on, showing the waveforms (rows) passed per second on the tqdm ``bar``."""
    t0, n = time.perf_counter(), 0
    for batch in batches:
        n += batch.num_rows
        bar.set_postfix_str(f"{n / max(time.perf_counter() - t0, 1e-9):,.0f} waveforms/s", refresh=False)
        yield batch
