"""A lasinfo-like summary of a LAS/LAZ point cloud without waveforms (for example the echo cloud of
``waveforest decompose``): header facts, coordinate system, counts, extent and each extra-bytes
dimension with its description and range, read in one streaming pass."""

from __future__ import annotations

import os
from pathlib import Path

import laspy
import numpy as np

from waveforest.io.las.file import fail
from waveforest.io.las.format import WAVEFORM_POINT_FORMATS
from waveforest.io.las.info import crs_description

POINT_FORMAT_BYTE = 104
"""Offset of the point data record format in every LAS 1.x public header."""


def is_point_cloud(path: str | os.PathLike) -> bool:
    """True for a LAS file (signature ``LASF``) whose point format carries no waveform packets;
    anything else (including a file that is not LAS) is left to the waveform reader's checks."""
    with open(path, "rb") as fh:
        head = fh.read(POINT_FORMAT_BYTE + 1)
    if len(head) <= POINT_FORMAT_BYTE or head[:4] != b"LASF":
        return False
    return (head[POINT_FORMAT_BYTE] & 0x3F) not in WAVEFORM_POINT_FORMATS


def summarise_point_cloud(path: str | os.PathLike, chunk_points: int = 1_000_000) -> str:
    """The summary as text, one fact per line (memory: one chunk of points)."""
    path = Path(path)
    try:
        reader = laspy.open(path)
    except Exception as exc:
        raise fail(path, f"cannot read the point cloud ({type(exc).__name__}: {exc})") from exc
    with reader:
        h = reader.header
        extra = list(h.point_format.extra_dimension_names)
        lo = {d: np.inf for d in extra}
        hi = {d: -np.inf for d in extra}
        returns, classes = {}, {}
        gps = [np.inf, -np.inf]
        n = 0
        for pts in reader.chunk_iterator(chunk_points):
            n += len(pts)
            first = np.asarray(pts.return_number) == 1
            for k, c in zip(*np.unique(np.asarray(pts.number_of_returns)[first], return_counts=True)):
                returns[int(k)] = returns.get(int(k), 0) + int(c)
            for k, c in zip(*np.unique(np.asarray(pts.classification), return_counts=True)):
                classes[int(k)] = classes.get(int(k), 0) + int(c)
            t = np.asarray(pts.gps_time)
            if t.size:
                gps = [min(gps[0], float(t.min())), max(gps[1], float(t.max()))]
            for d in extra:
                v = np.asarray(pts[d], np.float64)
                v = v[np.isfinite(v)]
                if v.size:
                    lo[d], hi[d] = min(lo[d], float(v.min())), max(hi[d], float(v.max()))
        described = {}
        for v in h.vlrs:
            if type(v).__name__ == "ExtraBytesVlr":
                described = {s.name.rstrip(b"\0").decode("ascii", "replace"):
                             s.description.rstrip(b"\0").decode("ascii", "replace") for s in v.extra_bytes_structs}
        lines = [
            f"file:                  {path}",
            f"version / format:      LAS {h.version}, point format {h.point_format.id} (no waveforms)",
            f"generating software:   {h.generating_software}",
            f"coordinate system:     {crs_description(h.vlrs, h.evlrs or ())}",
            f"points:                {n:,}",
            "returns per pulse:     " + ("; ".join(f"{k}: {c:,}" for k, c in sorted(returns.items())) or "none"),
            "classification:        " + ("; ".join(f"{k}: {c:,}" for k, c in sorted(classes.items())) or "none"),
            f"GPS time:              {gps[0]:.6f} - {gps[1]:.6f} s" if n else "GPS time:              none",
            "extent (x, y, z):      " + ", ".join(f"{a:.3f} - {b:.3f}" for a, b in zip(h.mins, h.maxs)),
        ]
        for d in extra:
            rng = f"{lo[d]:.6g} - {hi[d]:.6g}" if np.isfinite(lo[d]) else "no values"
            lines.append(f"extra bytes {d + ':':<14} {rng}  ({described.get(d, '')})")
    return "\n".join(lines)
