"""An echo point cloud: LAS 1.4 point format 6 with per-echo values as extra bytes (LAS 1.4 R15,
§2.6 point format 6 and §2.5.6 the Extra Bytes VLR, record id 4 of ``LASF_Spec``), LAS or LAZ.

Point format 9 keeps the waveforms: each echo points into its pulse's packet (R15 point format 9:
wave packet descriptor index, byte offset to waveform data, waveform packet size, return point
waveform location, ps after the first sample, and x(t), y(t), z(t), m/ps, so that the first
sample lies at ``P + L * (x(t), y(t), z(t))``); the source's Waveform Packet Descriptor VLRs
(record ids 100-354) are copied and the packets lie in a ``.wdp`` beside the file (global
encoding bit 2), a copy of the source's waveform data record (:func:`copy_waveform_data`).

Written through laspy (and lazrs for LAZ) in chunks, so memory does not grow with the file.
Each extra dimension is a 4-byte float, except ``pulse_id`` (uint64) and ``flags`` (uint8, the
pulse's decomposition flags, :data:`waveforest.sensor.decompose.FLAGS`), with its unit in its
description; a value that does not exist (a range without a known
sensor position) is written as the dimension's ``no_data`` value, 0.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

import laspy
import numpy as np

ECHO_DIMENSIONS = (
    ("pulse_id", "u8", "pulse number in the source file"),
    ("echo_time_ns", "f4", "ns: echo centre after 1st sample"),
    ("range_m", "f4", "m: sensor to echo; 0 = unknown"),
    ("amplitude_dn", "f4", "DN: Gaussian amplitude"),
    ("sigma_ns", "f4", "ns: Gaussian SD of the echo"),
    ("fwhm_ns", "f4", "ns: echo FWHM"),
    ("energy_dn_ns", "f4", "DN ns: echo area"),
    ("residual_dn", "f4", "DN: RMS fit residual of pulse"),
    ("flags", "u1", "pulse flags: 2 clip, 16/32 fit"),
    ("cross_section", "f4", "backscatter cross-section"),
)
"""(name, type, description) of the extra bytes, in record order (descriptions <= 32 characters)."""

NO_DATA_DIMENSIONS = ("range_m", "cross_section")
"""Dimensions that may not exist for a pulse (no sensor position): written as no_data = 0."""

WAVE_PACKET_FIELDS = (("wave_packet_index", "wavepacket_index"), ("wave_packet_offset", "wavepacket_offset"),
                      ("wave_packet_bytes", "wavepacket_size"), ("return_point_ps", "return_point_wave_location"),
                      ("x_t", "x_t"), ("y_t", "y_t"), ("z_t", "z_t"))
"""(echo column, laspy dimension) of the point format 9 wave packet fields."""


def echo_header(scales, offsets, vlrs=(), cross_section_unit: str = "relative", *,
                descriptors=None) -> laspy.LasHeader:
    """A LAS 1.4 point format 6 header (9 with ``descriptors``) with :data:`ECHO_DIMENSIONS` as extra bytes.

    ``vlrs``: laspy VLRs to carry over (the source file's coordinate system); a WKT one sets
    the WKT bit of the global encoding, as LAS 1.4 requires for point format 6.
    ``cross_section_unit``: ``"relative"`` or ``"m2"``, written into its description.
    ``descriptors``: the source's :class:`~waveforest.io.las.format.WavePacketDescriptor` per
    index: point format 9, one descriptor VLR each, packets external (global encoding bit 2).
    """
    header = laspy.LasHeader(point_format=6 if descriptors is None else 9, version="1.4")
    header.scales = np.asarray(scales, np.float64)
    header.offsets = np.asarray(offsets, np.float64)
    dims = []
    for name, kind, text in ECHO_DIMENSIONS:
        if name == "cross_section":
            text = "m2: backscatter cross-section" if cross_section_unit == "m2" else \
                "backscatter cross-section, rel."
        no_data = [0] if name in NO_DATA_DIMENSIONS else None
        dims.append(laspy.ExtraBytesParams(name=name, type=np.dtype(kind), description=text, no_data=no_data))
    header.add_extra_dims(dims)
    for v in vlrs:
        header.vlrs.append(v)
        if type(v).__name__ == "WktCoordinateSystemVlr":
            header.global_encoding.wkt = True
    if descriptors is not None:
        for i, d in sorted(descriptors.items()):
            header.vlrs.append(laspy.VLR(user_id="LASF_Spec", record_id=99 + int(i),
                                         description="waveform packet descriptor", record_data=d.body()))
        header.global_encoding.waveform_data_packets_external = True
    header.generating_software = "waveforest decompose"
    return header


class EchoCloudWriter:
    """Write echo chunks to a LAS/LAZ file (``compress``: LAZ through lazrs); use as a context manager.

    :meth:`write` takes a mapping of equal-length arrays: ``x, y, z`` (m), ``gps_time`` (s),
    ``scan_angle_deg``, ``return_number``, ``number_of_returns``, ``intensity`` (DN) and every
    name of :data:`ECHO_DIMENSIONS`; for point format 9 also the echo columns of
    :data:`WAVE_PACKET_FIELDS`.
    """

    def __init__(self, path: str | os.PathLike, header: laspy.LasHeader, compress: bool) -> None:
        self.path = Path(path)
        self.header = header
        self.compress = compress
        self.n_points = 0
        self._writer = None

    def __enter__(self) -> EchoCloudWriter:
        self._writer = laspy.open(self.path, mode="w", header=self.header, do_compress=self.compress,
                                  laz_backend=laspy.LazBackend.Lazrs if self.compress else None)
        return self

    def __exit__(self, *exc) -> None:
        self._writer.close()

    def write(self, echoes: Mapping[str, np.ndarray]) -> None:
        """Append one chunk of echoes."""
        m = len(echoes["x"])
        if m == 0:
            return
        rec = laspy.ScaleAwarePointRecord.zeros(m, header=self.header)
        rec.x, rec.y, rec.z = echoes["x"], echoes["y"], echoes["z"]
        rec.gps_time = echoes["gps_time"]
        angle = np.nan_to_num(np.asarray(echoes["scan_angle_deg"], np.float64))
        rec.scan_angle = np.clip(np.rint(angle / 0.006), -30000, 30000).astype(np.int16)
        rec.return_number = np.clip(echoes["return_number"], 1, 15)
        rec.number_of_returns = np.clip(echoes["number_of_returns"], 1, 15)
        rec.intensity = np.clip(np.rint(np.asarray(echoes["intensity"], np.float64)), 0, 65535).astype(np.uint16)
        for name, kind, _ in ECHO_DIMENSIONS:
            v = np.asarray(echoes[name])
            if name in NO_DATA_DIMENSIONS:
                v = np.where(np.isfinite(v), v, 0)
            rec[name] = v.astype(kind)
        if self.header.point_format.id == 9:
            for name, dim in WAVE_PACKET_FIELDS:
                rec[dim] = np.asarray(echoes[name]).astype(rec[dim].dtype)
        self._writer.write_points(rec)
        self.n_points += m


def copy_waveform_data(src, base: int, size: int, dst, chunk_bytes: int = 1 << 24) -> None:
    """Copy ``size`` bytes of ``src`` from byte ``base`` (a waveform data record: its 60-byte
    header and packets, :class:`waveforest.io.las.file.WaveformData`) to the file ``dst``, in
    chunks, so that byte offsets into the record stay valid in ``dst``."""
    with open(src, "rb") as fi, open(dst, "wb") as fo:
        fi.seek(base)
        left = int(size)
        while left > 0:
            buf = fi.read(min(chunk_bytes, left))
            if not buf:
                raise OSError(f"{src}: ends {left} bytes before the waveform data record does")
            fo.write(buf)
            left -= len(buf)
