"""Seeded random streams of the virtual campaign, one per purpose.

Every random draw of the campaign comes from a :class:`numpy.random.Generator` whose seed
sequence is the master seed plus a tuple of keys naming the purpose (e.g.
``("scene", "s10_03_007")``). A stream therefore does not depend on the order in which
other streams are used, on which datasets are generated, or on which effects are switched
on: switching ``xy_error`` on changes the recorded positions and nothing else.
"""

from __future__ import annotations

import zlib

import numpy as np


def _key(k: str | int) -> int:
    if isinstance(k, (int, np.integer)):
        if k < 0:
            raise ValueError(f"seed key {k}: expected a non-negative integer")
        return int(k)
    return zlib.crc32(str(k).encode("utf-8"))


def seed_sequence(seed: int, *keys: str | int) -> np.random.SeedSequence:
    """The seed sequence of the stream ``keys`` under the master ``seed``."""
    return np.random.SeedSequence(entropy=int(seed), spawn_key=tuple(_key(k) for k in keys))


def generator(seed: int, *keys: str | int) -> np.random.Generator:
    """A PCG64 generator for the stream ``keys`` under the master ``seed``."""
    return np.random.Generator(np.random.PCG64(seed_sequence(seed, *keys)))


def int_seed(seed: int, *keys: str | int) -> int:
    """A 31-bit integer seed for APIs that take an int (build_scene, trace)."""
    return int(seed_sequence(seed, *keys).generate_state(1, dtype=np.uint32)[0] >> 1)
