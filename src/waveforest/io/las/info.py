"""A lasinfo-style summary of a LAS waveform file (``waveforest info``).

Header facts come from :func:`waveforest.io.las.file.open_waveform_las`; counts (pulses, packets,
returns by number and per pulse, samples per packet, bounds, scan angles, AGC) from one streaming
pass over the points in GPS-time buckets; classification, the z outlier count and a grid of point
counts and highest points from a second streaming pass over the point records (no waveform bytes).
Memory stays bounded whatever the file size (the z percentiles come from a seeded sample of at
most :data:`Z_SAMPLE_POINTS` points).

z outliers: a point is one if its z lies below P1 - d or above P99 + d, with P1, P99 the 1st and
99th percentiles of the points' z and d = max(P99 - P1, :data:`Z_OUTLIER_MIN_M`): farther from the
central 98 % of the points than that band is wide (a canopy over its ground is not flagged).
"""

from __future__ import annotations

import os
import re
import warnings
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from laspy.vlrs.known import GeoAsciiParamsVlr, GeoKeyDirectoryVlr, WktCoordinateSystemVlr

from waveforest.io.las.file import LasWaveformFile, fail, open_point_reader
from waveforest.io.las.format import GE_WAVEFORM_EXTERNAL, GE_WAVEFORM_INTERNAL, GE_WKT
from waveforest.io.las.read import (
    DEFAULT_BUCKET_POINTS,
    DEFAULT_CHUNK_POINTS,
    WaveformPulseReader,
    sort_points,
)
from waveforest.rng import named_generator

HEADER_BOUNDS_TOL_M = 0.01
"""Header bounds within this of the points' bounds count as matching (writers round them), m."""

Z_OUTLIER_MIN_M = 10.0
"""Least distance beyond the 1st/99th z percentiles at which a point counts as a z outlier, m."""
Z_SAMPLE_POINTS = 1_000_000
"""Most points whose z places the percentiles (a seeded sample beyond that; exact below)."""
POINTS_PER_CELL = 4.0
"""Mean points per grid cell aimed at over the bounding box (sets the least cell size)."""
GRID_CELLS = 200
"""Most grid cells along the longer side of the extent."""

ASPRS_CLASSES = {
    0: "never classified", 1: "unclassified", 2: "ground", 3: "low vegetation", 4: "medium vegetation",
    5: "high vegetation", 6: "building", 7: "low point (noise)", 8: "model key point", 9: "water", 10: "rail",
    11: "road surface", 12: "overlap", 13: "wire guard", 14: "wire conductor", 15: "transmission tower",
    16: "wire connector", 17: "bridge deck", 18: "high noise",
}
"""ASPRS standard point classes (LAS 1.4 R15 table 17; 8 and 12 as in LAS 1.2/1.3)."""


def grid_cell_size(width_m: float, height_m: float, n: int, max_cells: int = GRID_CELLS) -> float:
    """Cell side, m, of a grid over a ``width_m`` x ``height_m`` box holding ``n`` points: at most
    ``max_cells`` along the longer side, and large enough for :data:`POINTS_PER_CELL` points a cell
    at the box's mean density (so a sparse file does not map as speckle)."""
    longer = max(float(width_m), float(height_m))
    if longer <= 0:
        return 1.0
    size = longer / max(int(max_cells), 1)
    area = float(width_m) * float(height_m)
    if n > 0 and area > 0:
        size = max(size, float(np.sqrt(POINTS_PER_CELL * area / n)))
    return size


@dataclass(frozen=True)
class PointGrid:
    """Points per cell and the highest point per cell (z outliers left out) on a square grid.

    ``count`` (ny, nx) int64, ``top_z`` (ny, nx) m (NaN where no point); row 0 at ``y0``.
    """

    x0: float
    y0: float
    cell_m: float
    count: np.ndarray
    top_z: np.ndarray

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) of the grid, m."""
        ny, nx = self.count.shape
        return self.x0, self.x0 + nx * self.cell_m, self.y0, self.y0 + ny * self.cell_m

    @property
    def covered_m2(self) -> float:
        """Area of the cells that hold at least one point, m²."""
        return float(np.count_nonzero(self.count)) * self.cell_m**2


@dataclass
class LasSummary:
    """Counts over the points of a LAS waveform file (see :func:`summarise`)."""

    las: LasWaveformFile
    n_points: int = 0
    n_pulses: int = 0
    n_packets: int = 0
    n_split_pulses: int = 0
    n_without_waveform: int = 0
    returns_by_number: Counter = field(default_factory=Counter)
    points_by_descriptor: Counter = field(default_factory=Counter)
    packets_by_samples: Counter = field(default_factory=Counter)
    mins: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    maxs: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    gps_range: tuple[float, float] = (np.inf, -np.inf)
    agc_dimension: str | None = None
    agc_range: tuple[float, float] = (np.inf, -np.inf)
    notes: list[str] = field(default_factory=list)
    points_per_pulse: Counter = field(default_factory=Counter)
    """Pulses (GPS times) by their number of points."""
    scan_range: tuple[float, float] = (np.inf, -np.inf)
    """Scan angles, degrees."""
    crs: str = "not stated"
    """The coordinate system from the WKT or GeoTIFF VLRs."""
    classes: Counter = field(default_factory=Counter)
    """Points by classification code."""
    z_window: tuple[float, float] = (-np.inf, np.inf)
    """z inside this is not an outlier, m (module docstring)."""
    z_sampled: bool = False
    """The z percentiles come from a sample (more than :data:`Z_SAMPLE_POINTS` points)."""
    n_z_outliers: int = 0
    grid: PointGrid | None = None

    @property
    def density(self) -> float:
        """Points per m² over the covered area of :attr:`grid` (NaN without)."""
        area = self.grid.covered_m2 if self.grid is not None else 0.0
        return self.n_points / area if area > 0 else float("nan")


def summarise(
    path: str | os.PathLike,
    *,
    agc_attribute: str | None = "user_data",
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    bucket_points: int = DEFAULT_BUCKET_POINTS,
    grid_cells: int = GRID_CELLS,
) -> LasSummary:
    """Check a LAS waveform file and count what it holds (no waveform bytes are decoded).

    ``grid_cells``: most cells of :attr:`LasSummary.grid` along the longer side of the extent.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        reader = WaveformPulseReader(path, agc_attribute=agc_attribute, chunk_points=chunk_points, bucket_points=bucket_points)
        s = LasSummary(las=reader.las)
        keep = min(1.0, Z_SAMPLE_POINTS / max(reader.las.n_points, 1))
        rng = named_generator("las_summary_z", 0)
        z_sample = []
        for rec in reader.buckets():
            if not len(rec):
                continue
            index = sort_points(rec)
            s.n_points += len(rec)
            s.n_pulses += index.n_pulses
            s.n_without_waveform += int(np.count_nonzero(index.chosen == len(rec)))
            s.points_per_pulse.update(dict(zip(*np.unique(np.diff(index.starts), return_counts=True))))
            scan = rec["scan"][np.isfinite(rec["scan"])]
            if scan.size:
                s.scan_range = (min(s.scan_range[0], float(scan.min())), max(s.scan_range[1], float(scan.max())))
            z = rec["xyz"][:, 2]
            z_sample.append(z if keep >= 1.0 else z[rng.random(len(z)) < keep])
            s.returns_by_number.update(dict(zip(*np.unique(rec["ret"], return_counts=True))))
            used = rec["wpi"] > 0
            s.points_by_descriptor.update(dict(zip(*np.unique(rec["wpi"][used], return_counts=True))))
            pk = np.zeros(int(used.sum()), dtype=[("gps", "<f8"), ("wpi", "u1"), ("off", "<u8")])
            pk["gps"], pk["wpi"], pk["off"] = rec["gps"][used], rec["wpi"][used], rec["off"][used]
            packets = np.unique(pk)
            s.n_packets += len(packets)
            per_pulse = np.unique(packets["gps"], return_counts=True)[1]
            s.n_split_pulses += int(np.count_nonzero(per_pulse > 1))
            n_samples = reader.las.descriptor_tables()["n_samples"][packets["wpi"]]
            s.packets_by_samples.update(dict(zip(*np.unique(n_samples, return_counts=True))))
            s.mins = np.minimum(s.mins, rec["xyz"].min(axis=0))
            s.maxs = np.maximum(s.maxs, rec["xyz"].max(axis=0))
            s.gps_range = (min(s.gps_range[0], float(rec["gps"].min())), max(s.gps_range[1], float(rec["gps"].max())))
            agc = rec["agc"][np.isfinite(rec["agc"])]
            if agc.size:
                s.agc_range = (min(s.agc_range[0], float(agc.min())), max(s.agc_range[1], float(agc.max())))
        s.agc_dimension = reader.stats.agc_dimension
        if s.n_points:
            z = np.concatenate(z_sample)
            p1, p99 = np.percentile(z, [1, 99])
            d = max(p99 - p1, Z_OUTLIER_MIN_M)
            s.z_window, s.z_sampled = (float(p1 - d), float(p99 + d)), keep < 1.0
            del z, z_sample
            _point_pass(s, int(chunk_points), grid_cells)
    s.notes = [str(w.message) for w in caught]
    return s


def _point_pass(s: LasSummary, chunk_points: int, grid_cells: int) -> None:
    """The second pass: classes, z outliers, the CRS and the point grid of ``s`` (points with a
    non-finite GPS time left out, as in the first pass)."""
    las = s.las
    w, h = s.maxs[:2] - s.mins[:2]
    cell = grid_cell_size(w, h, s.n_points, grid_cells)
    nx, ny = max(1, int(np.ceil(w / cell))), max(1, int(np.ceil(h / cell)))
    count = np.zeros(nx * ny, np.int64)
    top = np.full(nx * ny, -np.inf)
    lo, hi = s.z_window
    try:
        reader = open_point_reader(las)
    except Exception as exc:
        raise fail(las.path, f"cannot open the point records ({type(exc).__name__}: {exc})") from exc
    with reader:
        s.crs = crs_description(reader.header.vlrs, projection_records(las.projection_evlrs))
        reader.header.point_count = las.n_points
        for pts in reader.chunk_iterator(chunk_points):
            arr = pts.array
            ok = np.isfinite(arr["gps_time"])
            xyz = [(arr[k][ok] * las.scales[i] + las.offsets[i]) for i, k in enumerate("XYZ")]
            cls = np.asarray(pts.classification, dtype=np.int64)[ok]
            s.classes.update(dict(zip(*np.unique(cls, return_counts=True))))
            inside = (xyz[2] >= lo) & (xyz[2] <= hi)
            s.n_z_outliers += int(np.count_nonzero(~inside))
            ix = np.clip(((xyz[0] - s.mins[0]) / cell).astype(np.int64), 0, nx - 1)
            iy = np.clip(((xyz[1] - s.mins[1]) / cell).astype(np.int64), 0, ny - 1)
            at = iy * nx + ix
            count += np.bincount(at, minlength=nx * ny)
            np.maximum.at(top, at[inside], xyz[2][inside])
    top[~np.isfinite(top)] = np.nan
    s.grid = PointGrid(float(s.mins[0]), float(s.mins[1]), cell, count.reshape(ny, nx), top.reshape(ny, nx))


PROJECTION_RECORDS = {cls.official_record_ids()[0]: cls
                      for cls in (WktCoordinateSystemVlr, GeoKeyDirectoryVlr, GeoAsciiParamsVlr)}
"""laspy's parsers of the coordinate-system records, by record id."""


def projection_records(pairs) -> list:
    """laspy records parsed from ``(record id, body)`` pairs (:attr:`LasWaveformFile.projection_evlrs`);
    a record laspy cannot parse is left out."""
    out = []
    for rid, body in pairs:
        if rid in PROJECTION_RECORDS:
            record = PROJECTION_RECORDS[rid]()
            try:
                record.parse_record_data(body)
            except Exception:  # a garbled CRS record reads as no CRS
                continue
            out.append(record)
    return out


def crs_description(vlrs, evlrs=()) -> str:
    """The coordinate system named by laspy-parsed VLRs or EVLRs (LAS 1.4 may keep it in either):
    the WKT record's name and EPSG code, else the GeoTIFF keys' EPSG code and citation;
    ``"not stated"`` without either."""
    records = [(v, "VLR") for v in vlrs] + [(v, "EVLR") for v in evlrs]
    for v, kind in records:
        if type(v).__name__ == "WktCoordinateSystemVlr":
            text = str(getattr(v, "string", "") or "").strip("\x00 \n")
            name = re.match(r'\s*\w+\[\s*"([^"]*)"', text)
            code = re.search(r'AUTHORITY\[\s*"EPSG"\s*,\s*"?(\d+)"?\s*\]\s*\]\s*$', text)
            if name or code:
                label = name.group(1) if name else "unnamed"
                epsg = f"EPSG:{code.group(1)}" if code and code.group(1) != "0" else "no EPSG code"
                return f"{label} ({epsg}; WKT {kind})"
    keys, ascii_, where = {}, "", "VLR"
    for v, kind in records:
        name = type(v).__name__
        if name == "GeoKeyDirectoryVlr" and not keys:
            keys, where = {int(k.id): k for k in v.geo_keys}, kind
        elif name == "GeoAsciiParamsVlr" and not ascii_:
            ascii_ = "".join(getattr(v, "strings", []) or [])
    if not keys:
        return "not stated"
    code = next((int(keys[k].value_offset) for k in (3072, 2048) if k in keys and keys[k].tiff_tag_location == 0
                 and int(keys[k].value_offset) not in (0, 32767)), None)
    cite = ""
    for k in (3073, 1026, 2049):
        g = keys.get(k)
        if g is not None and g.tiff_tag_location == 34737 and ascii_:
            cite = ascii_[g.value_offset:g.value_offset + g.count].strip("|\x00 ")
            if cite:
                break
    epsg = f"EPSG:{code}" if code else "no EPSG code"
    suffix = "GeoTIFF keys" if where == "VLR" else "GeoTIFF keys, EVLR"
    return f"{cite or 'user-defined'} ({epsg}; {suffix})"


def _n(v) -> str:
    return f"{int(v):,}"


def format_summary(s: LasSummary) -> str:
    """The summary as lasinfo-like text (one fact per line)."""
    las = s.las
    wf = las.waveform
    ge = las.global_encoding
    bits = [name for bit, name in ((GE_WAVEFORM_INTERNAL, "waveforms internal"), (GE_WAVEFORM_EXTERNAL, "waveforms external"), (GE_WKT, "WKT")) if ge & bit]
    if wf.storage == "external":
        storage = f"external: {wf.path.name} ({_n(wf.size)} bytes, record header {'ok' if wf.header_ok else 'MALFORMED'})"
    else:
        storage = f"internal: waveform record at byte {_n(wf.base)} ({_n(wf.size - 60)} bytes of packets, header {'ok' if wf.header_ok else 'MALFORMED'})"
    extra = f", extra bytes: {', '.join(las.extra_dimension_names)}" if las.extra_dimension_names else ""
    lines = [
        f"file:                  {las.path} ({_n(las.file_size)} bytes)",
        f"LAS version:           {las.version}",
        f"system identifier:     {las.system_identifier}",
        f"generating software:   {las.generating_software}",
        f"creation (day, year):  {las.creation[0]}, {las.creation[1]}",
        f"point format:          {las.point_format} (record length {las.record_length} bytes{extra}"
        f"{'; LAZ-compressed' if las.compressed else ''})",
        f"points:                {_n(s.n_points)} (header: {_n(las.n_points)})",
        f"global encoding:       {ge} ({', '.join(bits) or 'no waveform bits'})",
        f"waveform storage:      {storage}",
    ]
    used = sorted(int(k) for k in s.points_by_descriptor)
    empty = [i for i, d in las.descriptors.items() if d.empty]
    unused = [i for i in las.descriptors if i not in used]
    lines.append(
        f"descriptors:           {len(las.descriptors)} defined, {len(used)} in use, "
        f"{len(unused)} unused ({len(empty)} of them empty: 0 samples or 0 ps)"
    )
    lines.append("  index  bits  compression  samples  spacing_ps  gain          offset        points")
    for i in used:
        d = las.descriptors[i]
        lines.append(
            f"  {i:>5}  {d.bits:>4}  {d.compression:>11}  {d.n_samples:>7}  {d.spacing_ps:>10}  "
            f"{d.gain:<12.6g}  {d.offset:<12.6g}  {_n(s.points_by_descriptor[i])}"
        )
    lines += [
        f"pulses (GPS times):    {_n(s.n_pulses)}"
        + (f" ({_n(s.n_without_waveform)} without waveform)" if s.n_without_waveform else ""),
        f"packets:               {_n(s.n_packets)} ({_n(s.n_split_pulses)} pulses with returns in several packets)",
        "returns by number:     " + ", ".join(f"{int(k)}: {_n(v)}" for k, v in sorted(s.returns_by_number.items())),
        "samples per packet:    " + ", ".join(f"{int(k)}: {_n(v)} packets" for k, v in sorted(s.packets_by_samples.items())),
        "AGC attribute:         "
        + (
            f"{s.agc_dimension} (range {s.agc_range[0]:g} .. {s.agc_range[1]:g})"
            if s.agc_dimension
            else "none (AGC normalisation will be skipped)"
        ),
    ]
    if s.n_points:
        lines += [
            f"GPS time:              {s.gps_range[0]:.6f} .. {s.gps_range[1]:.6f} s",
            f"bounds min (x, y, z):  {s.mins[0]:.3f} {s.mins[1]:.3f} {s.mins[2]:.3f}",
            f"bounds max (x, y, z):  {s.maxs[0]:.3f} {s.maxs[1]:.3f} {s.maxs[2]:.3f}",
            "points per pulse:      " + ", ".join(f"{int(k)}: {_n(v)} pulses" for k, v in sorted(s.points_per_pulse.items())),
            "scan angle:            " + (f"{s.scan_range[0]:.3f} .. {s.scan_range[1]:.3f} deg"
                                         if np.isfinite(s.scan_range[0]) else "n/a"),
        ]
    if s.grid is not None:
        lines += [
            "classification:        " + ", ".join(f"{int(k)} {ASPRS_CLASSES.get(int(k), 'user-defined')}: {_n(v)}"
                                                  for k, v in sorted(s.classes.items())),
            f"z outliers:            {_n(s.n_z_outliers)} outside {s.z_window[0]:.3f} .. {s.z_window[1]:.3f} "
            f"(P1 - d .. P99 + d, d = max(P99 - P1, {Z_OUTLIER_MIN_M:g} m){'; percentiles from a sample' if s.z_sampled else ''})",
            f"covered area:          {s.grid.covered_m2:.1f} m2 ({s.grid.cell_m:.2f}-m cells holding a point); "
            f"{s.density:.2f} points/m2",
            f"coordinate system:     {s.crs}",
        ]
    if s.n_points:
        differ = not (
            np.allclose(las.header_mins, s.mins, rtol=0, atol=HEADER_BOUNDS_TOL_M)
            and np.allclose(las.header_maxs, s.maxs, rtol=0, atol=HEADER_BOUNDS_TOL_M)
        )
        lines.append(
            "header bounds:         "
            f"{las.header_mins[0]:.3f} {las.header_mins[1]:.3f} {las.header_mins[2]:.3f} .. "
            f"{las.header_maxs[0]:.3f} {las.header_maxs[1]:.3f} {las.header_maxs[2]:.3f}"
            + (" (differ from the points': e.g. those of a whole flight line)" if differ else "")
        )
    for note in s.notes:
        lines.append(f"note: {note}")
    return "\n".join(lines)
