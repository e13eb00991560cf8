"""Thread counts of the tracer's Numba kernels and Embree calls."""

from __future__ import annotations

import numba

MIN_PARALLEL_RAYS = 8192
"""Calls with fewer rays run on one thread (thread start-up and barriers cost more than they
save, and far more when other jobs occupy the cores)."""


def default_threads() -> int:
    """Numba's current thread count (set by ``--threads``), at least 1."""
    return max(1, int(numba.get_num_threads()))


class NumbaThreads:
    """Context: Numba's (thread-local) thread count set to ``threads`` (None: unchanged)."""

    def __init__(self, threads: int | None) -> None:
        self.threads = threads

    def __enter__(self):
        self.prev = numba.get_num_threads()
        if self.threads is not None:
            numba.set_num_threads(max(1, min(int(self.threads), numba.config.NUMBA_NUM_THREADS)))

    def __exit__(self, *exc):
        numba.set_num_threads(self.prev)
