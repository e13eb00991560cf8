"""Slow, obviously correct references for the LAS waveform I/O (tests only).

Written straight from the LAS 1.4 R15 text with :mod:`struct`, one point and one packet at
a time, sharing no code with ``waveforest.io`` (nor laspy), so that the fast reader and the
writer are checked against an independent reading of the bytes.
"""

from __future__ import annotations

import math
import struct
from collections import defaultdict
from pathlib import Path

import numpy as np

RANGE_PER_NS = 299_792_458.0e-9 / 2.0  # m per ns of two-way time, written out independently

RIEGL = Path(__file__).parent / "data" / "real" / "riegl_fwf.las"
"""A real RIEGL waveform LAS nobody here wrote (tests/data/real/README.md), with its .wdp."""

# per point format: struct of the fields before the wave packet, and their names
_CORE = {
    4: ("<lllHBBbBHd", ["X", "Y", "Z", "intensity", "bits", "cls", "scan", "user_data", "psid", "gps"]),
    5: ("<lllHBBbBHdHHH", ["X", "Y", "Z", "intensity", "bits", "cls", "scan", "user_data", "psid", "gps", "r", "g", "b"]),
    9: ("<lllHBBBBhHd", ["X", "Y", "Z", "intensity", "bits", "flags", "cls", "user_data", "scan", "psid", "gps"]),
    10: ("<lllHBBBBhHdHHHH", ["X", "Y", "Z", "intensity", "bits", "flags", "cls", "user_data", "scan", "psid", "gps", "r", "g", "b", "nir"]),
}
_WAVE = "<BQIffff"


def reference_header(path: Path) -> dict:
    """The public header block fields the waveform reader needs."""
    with open(path, "rb") as fh:
        raw = fh.read(375)
    assert raw[:4] == b"LASF"
    h = {
        "global_encoding": struct.unpack_from("<H", raw, 6)[0],
        "version": (raw[24], raw[25]),
        "header_size": struct.unpack_from("<H", raw, 94)[0],
        "offset_to_points": struct.unpack_from("<I", raw, 96)[0],
        "n_vlrs": struct.unpack_from("<I", raw, 100)[0],
        "point_format": raw[104] & 0x3F,
        "record_length": struct.unpack_from("<H", raw, 105)[0],
        "n_points": struct.unpack_from("<I", raw, 107)[0],
        "scale": struct.unpack_from("<3d", raw, 131),
        "offset": struct.unpack_from("<3d", raw, 155),
        "start_of_waveform": struct.unpack_from("<Q", raw, 227)[0],
    }
    if raw[25] >= 4:
        h["start_of_evlr"] = struct.unpack_from("<Q", raw, 235)[0]
        h["n_evlrs"] = struct.unpack_from("<I", raw, 243)[0]
        h["n_points"] = struct.unpack_from("<Q", raw, 247)[0] or h["n_points"]
    return h


def reference_descriptors(path: Path) -> dict[int, dict]:
    """Waveform packet descriptors by index, from the VLRs (one VLR at a time)."""
    h = reference_header(path)
    out = {}
    with open(path, "rb") as fh:
        fh.seek(h["header_size"])
        for _ in range(h["n_vlrs"]):
            _, user, rid, length, _ = struct.unpack("<H16sHH32s", fh.read(54))
            body = fh.read(length)
            if user.rstrip(b"\0") == b"LASF_Spec" and 100 <= rid <= 354:
                bits, comp, ns, spacing, gain, off = struct.unpack("<BBIIdd", body[:26])
                out[rid - 99] = dict(bits=bits, compression=comp, n_samples=ns, spacing_ps=spacing, gain=gain, offset=off)
    return out


def reference_points(path: Path) -> list[dict]:
    """Every point record, in file order, as a dict of plain Python numbers."""
    h = reference_header(path)
    fmt, names = _CORE[h["point_format"]]
    core = struct.calcsize(fmt)
    pts = []
    with open(path, "rb") as fh:
        fh.seek(h["offset_to_points"])
        for i in range(h["n_points"]):
            raw = fh.read(h["record_length"])
            p = dict(zip(names, struct.unpack_from(fmt, raw, 0)))
            wpi, off, size, loc, xt, yt, zt = struct.unpack_from(_WAVE, raw, core)
            p.update(wpi=wpi, off=off, size=size, loc=loc, xt=xt, yt=yt, zt=zt, index=i)
            p["x"] = p["X"] * h["scale"][0] + h["offset"][0]
            p["y"] = p["Y"] * h["scale"][1] + h["offset"][1]
            p["z"] = p["Z"] * h["scale"][2] + h["offset"][2]
            if h["point_format"] in (4, 5):
                p["ret"], p["nret"] = p["bits"] & 7, (p["bits"] >> 3) & 7
                p["scan_deg"] = float(p["scan"])
            else:
                p["ret"], p["nret"] = p["bits"] & 15, p["bits"] >> 4
                p["scan_deg"] = p["scan"] * 0.006
            pts.append(p)
    return pts


def reference_waveform_base(path: Path) -> tuple[Path, int]:
    """File holding the packets and the position byte offsets count from."""
    h = reference_header(path)
    if h["global_encoding"] & 4:
        return path.with_suffix(".wdp"), 0
    if h["start_of_waveform"]:
        return path, h["start_of_waveform"]
    with open(path, "rb") as fh:  # LAS 1.4: find EVLR 65535
        pos = h["start_of_evlr"]
        for _ in range(h["n_evlrs"]):
            fh.seek(pos)
            _, user, rid, length, _ = struct.unpack("<H16sHQ32s", fh.read(60))
            if rid == 65535:
                return path, pos
            pos += 60 + length
    raise AssertionError("no waveform data")


def reference_pulses(path: Path, agc_attribute: str | None = "user_data") -> list[dict]:
    """Pulses of a LAS waveform file, grouped by GPS time, in GPS-time order.

    Each pulse: gps, samples (list of int), sampling_ns, gain, offset, anchor (3,),
    dir (3,), echoes (list of (x, y, z, time_ns, intensity)), scan_deg, agc, n_echoes.
    The conventions are those of the module docstring of ``waveforest.io.las.read``.
    """
    path = Path(path)
    desc = reference_descriptors(path)
    wpath, base = reference_waveform_base(path)
    groups = defaultdict(list)
    for p in reference_points(path):
        groups[p["gps"]].append(p)
    pulses = []
    with open(wpath, "rb") as wf:
        for gps in sorted(groups):
            pts = sorted(groups[gps], key=lambda p: (p["ret"], p["off"]))
            chosen = next((p for p in pts if p["wpi"] > 0), None)
            if chosen is None:
                continue
            d = desc[chosen["wpi"]]
            nb = {8: 1, 16: 2, 32: 4}[d["bits"]]
            wf.seek(base + chosen["off"])
            raw = wf.read(d["n_samples"] * nb)
            code = {1: "B", 2: "H", 4: "I"}[nb]
            samples = list(struct.unpack(f"<{d['n_samples']}{code}", raw))
            L = float(chosen["loc"])
            dv = (float(chosen["xt"]), float(chosen["yt"]), float(chosen["zt"]))
            anchor = (chosen["x"] + L * dv[0], chosen["y"] + L * dv[1], chosen["z"] + L * dv[2])
            norm = math.sqrt(sum(v * v for v in dv))
            direction = tuple(-v / norm for v in dv)
            echoes = []
            for p in pts:
                if p["off"] == chosen["off"] and p["wpi"] == chosen["wpi"]:
                    t = p["loc"] / 1000.0
                else:
                    t = sum((q - a) * u for q, a, u in zip((p["x"], p["y"], p["z"]), anchor, direction)) / RANGE_PER_NS
                echoes.append((p["x"], p["y"], p["z"], t, float(p["intensity"])))
            agc = float(pts[0]["user_data"]) if agc_attribute == "user_data" else float("nan")
            pulses.append(
                dict(
                    gps=gps,
                    samples=samples,
                    sampling_ns=d["spacing_ps"] / 1000.0,
                    gain=d["gain"],
                    offset=d["offset"],
                    anchor=anchor,
                    dir=direction,
                    echoes=echoes,
                    scan_deg=pts[0]["scan_deg"],
                    agc=agc,
                    n_echoes=len(pts),
                )
            )
    return pulses


def reference_gather(buf: np.ndarray, byte_offset, n_samples, sample_bytes) -> tuple[np.ndarray, np.ndarray]:
    """Reference of ``waveforest.io.las.gather.gather_samples``: int.from_bytes per sample."""
    data = bytes(np.asarray(buf, dtype=np.uint8))
    values, offsets = [], [0]
    for o, n, b in zip(byte_offset, n_samples, sample_bytes):
        for k in range(int(n)):
            start = int(o) + k * int(b)
            values.append(int.from_bytes(data[start : start + int(b)], "little", signed=False))
        offsets.append(offsets[-1] + int(n))
    return np.array(values, dtype=np.float32), np.array(offsets, dtype=np.int64)


# -- file surgery for the messy-file and error tests ----------------------------------------

_POINT_FIELD_OFFSETS = {
    # byte offset of fields inside a point record, per point format (LAS 1.4 R15 tables)
    4: {"X": 0, "intensity": 12, "bits": 14, "user_data": 17, "gps": 20, "wpi": 28, "off": 29, "size": 37, "loc": 41, "xt": 45},
    5: {"X": 0, "intensity": 12, "bits": 14, "user_data": 17, "gps": 20, "wpi": 34, "off": 35, "size": 43, "loc": 47, "xt": 51},
    9: {"X": 0, "intensity": 12, "bits": 14, "user_data": 17, "gps": 22, "wpi": 30, "off": 31, "size": 39, "loc": 43, "xt": 47},
    10: {"X": 0, "intensity": 12, "bits": 14, "user_data": 17, "gps": 22, "wpi": 38, "off": 39, "size": 47, "loc": 51, "xt": 55},
}


def point_field_position(path: Path, index: int, field: str) -> int:
    """Absolute file position of ``field`` of point ``index``."""
    h = reference_header(path)
    return h["offset_to_points"] + index * h["record_length"] + _POINT_FIELD_OFFSETS[h["point_format"]][field]


def vlr_body_position(path: Path, record_id: int) -> int:
    """Absolute file position of the body of the VLR with ``record_id``."""
    h = reference_header(path)
    with open(path, "rb") as fh:
        pos = h["header_size"]
        for _ in range(h["n_vlrs"]):
            fh.seek(pos)
            _, _, rid, length, _ = struct.unpack("<H16sHH32s", fh.read(54))
            if rid == record_id:
                return pos + 54
            pos += 54 + length
    raise KeyError(record_id)


def patch(path: Path, pos: int, fmt: str, *values) -> None:
    """Overwrite bytes at ``pos`` with ``struct.pack(fmt, *values)``."""
    with open(path, "r+b") as fh:
        fh.seek(pos)
        fh.write(struct.pack(fmt, *values))
