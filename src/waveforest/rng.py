"""Seeds and random streams: the one home of every seed derivation (docs/design.md).

Two derivations, each fixed forever because result tables depend on them bit for bit:

- **Keyed streams** (the virtual campaign): :func:`stream_sequence`, :func:`stream_generator`,
  :func:`stream_seed31`. The master seed is the entropy and the keys naming the purpose
  (e.g. ``("scene", "s10_03_007")``) are the spawn key, each string key as its
  :func:`stable_hash`. A stream does not depend on the order in which other streams are
  used, on which datasets are generated, or on which effects are switched on.
- **Hashed parts** (the forward model and the stages that use it): :func:`hashed_sequence`,
  :func:`hashed_seed63`. All parts (master seed, dataset, purpose, ids) form the entropy
  list, strings as their :func:`stable_hash`.

:func:`hash_ids` scrambles integer ids under a key with the SplitMix64 finaliser (per-pulse
ranks, instance and chunk assignment). Every function here is pure and process-independent.
"""

from __future__ import annotations

import zlib

import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_M64 = 0xFFFFFFFFFFFFFFFF


def stable_hash(*parts) -> int:
    """CRC-32 of the parts' ``str`` joined by U+001F: an int in [0, 2^32), the same everywhere."""
    text = "\x1f".join(str(p) for p in parts)
    return zlib.crc32(text.encode("utf-8"))


def hash_ids(key: int, ids) -> np.ndarray:
    """SplitMix64 finaliser of integer ids under a key, vectorised.

    ``z = (ids as uint64) ^ (key mod 2^64) + 0x9E3779B97F4A7C15``, then the two
    xor-shift-multiply rounds and the final xor-shift of SplitMix64 (wrapping arithmetic).

    Parameters
    ----------
    key : int
        E.g. :func:`stable_hash` of the seed, dataset and purpose.
    ids : (n,) int

    Returns
    -------
    (n,) uint64, uniformly scrambled; the same in every process.
    """
    with np.errstate(over="ignore"):
        z = np.asarray(ids, dtype=np.int64).astype(np.uint64) ^ np.uint64(int(key) & _M64)
        z = z + _GOLDEN
        z = (z ^ (z >> np.uint64(30))) * _MIX1
        z = (z ^ (z >> np.uint64(27))) * _MIX2
        return z ^ (z >> np.uint64(31))


# -- keyed streams (the virtual campaign) ---------------------------------------------------------

def _key(k: str | int) -> int:
    """A spawn-key entry: a non-negative int as is, anything else as its :func:`stable_hash`.

    Raises ValueError for a negative int.
    """
    if isinstance(k, (int, np.integer)):
        if k < 0:
            raise ValueError(f"seed key {k}: expected a non-negative integer")
        return int(k)
    return stable_hash(k)


def stream_sequence(seed: int, *keys: str | int) -> np.random.SeedSequence:
    """``SeedSequence(entropy=seed, spawn_key=keys)`` of the stream ``keys`` under the master ``seed``."""
    return np.random.SeedSequence(entropy=int(seed), spawn_key=tuple(_key(k) for k in keys))


def stream_generator(seed: int, *keys: str | int) -> np.random.Generator:
    """A PCG64 generator for the stream ``keys`` under the master ``seed``."""
    return np.random.Generator(np.random.PCG64(stream_sequence(seed, *keys)))


def stream_seed31(seed: int, *keys: str | int) -> int:
    """A 31-bit integer seed (in [0, 2^31)) of the stream ``keys``, for APIs that take an int."""
    return int(stream_sequence(seed, *keys).generate_state(1, dtype=np.uint32)[0] >> 1)


# -- hashed parts (the forward model) -------------------------------------------------------------

def hashed_sequence(*parts) -> np.random.SeedSequence:
    """``SeedSequence([p0, p1, ...])`` of ints and strings (strings enter as :func:`stable_hash`)."""
    entropy = [int(p) if isinstance(p, (int, np.integer)) else stable_hash(p) for p in parts]
    return np.random.SeedSequence(entropy)


def hashed_seed63(*parts) -> int:
    """A non-negative 63-bit integer seed (in [0, 2^63)) derived from ``parts``."""
    return int(hashed_sequence(*parts).generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))
