"""A lasinfo-style summary of a LAS waveform file (``waveforest info``).

Header facts come from :func:`waveforest.io.las.file.open_waveform_las`; counts (pulses, packets,
returns by number, samples per packet, bounds, AGC) from one streaming pass over the
points in GPS-time buckets, so the summary works on files larger than memory.
"""

from __future__ import annotations

import os
import warnings
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from waveforest.io.las.format import GE_WAVEFORM_EXTERNAL, GE_WAVEFORM_INTERNAL, GE_WKT
from waveforest.io.las.read import (
    DEFAULT_BUCKET_POINTS,
    DEFAULT_CHUNK_POINTS,
    LasWaveformFile,
    WaveformPulseReader,
    sort_points,
)

HEADER_BOUNDS_TOL_M = 0.01
"""Header bounds within this of the points' bounds count as matching (writers round them), m."""


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


def summarise(
    path: str | os.PathLike,
    *,
    agc_attribute: str | None = "user_data",
    chunk_points: int = DEFAULT_CHUNK_POINTS,
    bucket_points: int = DEFAULT_BUCKET_POINTS,
) -> LasSummary:
    """Check a LAS waveform file and count what it holds (no waveform bytes are decoded)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        reader = WaveformPulseReader(path, agc_attribute=agc_attribute, chunk_points=chunk_points, bucket_points=bucket_points)
        s = LasSummary(las=reader.las)
        for rec in reader.buckets():
            if not len(rec):
                continue
            index = sort_points(rec)
            s.n_points += len(rec)
            s.n_pulses += index.n_pulses
            s.n_without_waveform += int(np.count_nonzero(index.chosen == len(rec)))
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
    s.notes = [str(w.message) for w in caught]
    return s


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
