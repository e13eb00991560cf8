"""Decode waveform packets out of a byte buffer (a memory map of the waveform data).

The hot loop of ``ingest``, vectorised over pulses: packets of one layout (samples x bytes
per sample) are copied in one fancy-indexing call on a sliding-window view of the buffer,
so no Python loop runs over pulses or samples and no index array the size of the output
is built. Samples are little-endian unsigned 8-, 16- or 32-bit integers (LAS compression
type 0), returned as float32.

NumPy rather than a Numba kernel on purpose: ``ingest`` does not import Numba (llvmlite's
resident memory counts against ingest's memory budget; the figures are in
docs/validation.md, "Speed").
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

SAMPLE_DTYPES = {1: np.dtype("u1"), 2: np.dtype("<u2"), 4: np.dtype("<u4")}
"""Little-endian unsigned sample types by bytes per sample."""
SCATTER_ROWS = 4096
"""Packets placed per step when several layouts mix (bounds the scatter index to ~8 MB)."""


def gather_samples(
    buf: np.ndarray, byte_offset: np.ndarray, n_samples: np.ndarray, sample_bytes: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Copy waveform packets out of ``buf`` as one flat float32 array.

    Parameters
    ----------
    buf : (n_bytes,) uint8
        The waveform data (e.g. ``np.frombuffer`` of a memory map), byte 0 being the origin
        of the packets' byte offsets.
    byte_offset : (n,) int64
        Start of each packet in ``buf``, bytes.
    n_samples : (n,) int64
        Samples per packet.
    sample_bytes : (n,) int64
        1, 2 or 4: bytes per (little-endian, unsigned) sample.

    Returns
    -------
    samples : (n_samples.sum(),) float32
        The packets one after another, DN.
    offsets : (n + 1,) int64
        Packet ``i`` is ``samples[offsets[i]:offsets[i + 1]]``.

    Raises
    ------
    ValueError
        On a wrong dtype or shape, a sample size other than 1, 2, 4, or a packet that
        reaches outside ``buf``.
    """
    if not isinstance(buf, np.ndarray) or buf.dtype != np.uint8 or buf.ndim != 1:
        raise ValueError("buf must be a 1-D uint8 array")
    byte_offset = np.asarray(byte_offset, dtype=np.int64)
    n_samples = np.asarray(n_samples, dtype=np.int64)
    sample_bytes = np.asarray(sample_bytes, dtype=np.int64)
    n = byte_offset.shape[0] if byte_offset.ndim == 1 else -1
    if n < 0 or n_samples.shape != (n,) or sample_bytes.shape != (n,):
        raise ValueError("byte_offset, n_samples and sample_bytes must be 1-D arrays of one length")
    if n and not np.all(np.isin(sample_bytes, list(SAMPLE_DTYPES))):
        raise ValueError(f"sample_bytes must be one of {tuple(SAMPLE_DTYPES)}")
    if n and (np.any(byte_offset < 0) or np.any(n_samples < 0)):
        raise ValueError("byte offsets and sample counts must be >= 0")
    packet_bytes = n_samples * sample_bytes
    end = byte_offset + packet_bytes
    if n and int(end.max()) > buf.shape[0]:
        i = int(np.argmax(end))
        raise ValueError(
            f"packet at byte {byte_offset[i]} ({packet_bytes[i]} bytes) ends beyond the buffer ({buf.shape[0]} bytes)"
        )
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(n_samples, out=offsets[1:])
    out = np.empty(int(offsets[-1]), dtype=np.float32)
    if not out.size:
        return out, offsets
    layout = n_samples * 8 + sample_bytes
    layouts = np.unique(layout[n_samples > 0])
    for key in layouts:  # one step per packet layout (a handful per file), vectorised over pulses
        ns, nb = int(key) // 8, int(key) % 8
        window = sliding_window_view(buf, ns * nb)
        if len(layouts) == 1 and np.all(n_samples == ns):
            out[:] = window[byte_offset].view(SAMPLE_DTYPES[nb]).ravel()
            break
        rows = np.flatnonzero(layout == key)
        for r0 in range(0, len(rows), SCATTER_ROWS):
            r = rows[r0 : r0 + SCATTER_ROWS]
            values = window[byte_offset[r]].view(SAMPLE_DTYPES[nb])
            out[(offsets[r][:, None] + np.arange(ns)).ravel()] = values.ravel()
    return out, offsets
