"""Independent units of work (a scene to build and trace) shared over worker threads.

Each worker thread runs its unit with single-threaded Numba kernels and MCRT, so that the
serial parts of one unit (vegetation generation, the Embree BVH build, table assembly) overlap
with the tracing of another on every core. The heavy parts release the GIL (Embree through
ctypes, ``nogil`` Numba kernels, most of NumPy); threads need no start-up, no pickling and no
``__main__`` guard in a caller's script. A unit's result must not depend on the thread that
runs it: callers seed every unit from the master seed and the unit's own id.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from typing import TypeVar

import numba

T = TypeVar("T")
R = TypeVar("R")

QUEUE_PER_WORKER = 2
"""Units queued per worker at a time (bounds the memory of scenes in flight)."""


def _serial(fn: Callable[[T], R], item: T) -> R:
    numba.set_num_threads(1)  # thread-local: this worker's kernels run serially
    return fn(item)


def unordered_map(fn: Callable[[T], R], items: Sequence[T], workers: int) -> Iterator[tuple[int, R]]:
    """``(index, fn(items[index]))`` in the order the units finish.

    ``workers`` <= 1 or a single item: run in the calling thread, in order, with the caller's
    Numba thread count (the MCRT of one unit then uses every thread). Otherwise each of
    ``workers`` threads runs one unit at a time with one Numba thread; at most
    :data:`QUEUE_PER_WORKER` units per worker are submitted ahead. An exception in a unit
    cancels the units not started and is raised here.
    """
    if workers <= 1 or len(items) < 2:
        for i, item in enumerate(items):
            yield i, fn(item)
        return
    with ThreadPoolExecutor(max_workers=min(workers, len(items)), thread_name_prefix="waveforest-unit") as pool:
        todo = iter(range(len(items)))
        pending = {}
        try:
            for i in todo:
                pending[pool.submit(_serial, fn, items[i])] = i
                if len(pending) >= QUEUE_PER_WORKER * workers:
                    break
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for f in done:
                    i = pending.pop(f)
                    nxt = next(todo, None)
                    if nxt is not None:
                        pending[pool.submit(_serial, fn, items[nxt])] = nxt
                    yield i, f.result()
        finally:
            for f in pending:
                f.cancel()
