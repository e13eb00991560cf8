"""Seeds and random streams: the one home of every seed derivation (docs/design.md).

No other module builds a ``SeedSequence``, a bit generator or a ``Generator``, nor spawns
or draws seed words: each asks for a stream here (``tests/test_rng.py`` checks it). Three
derivations, each fixed forever because result tables depend on them bit for bit:

- **Keyed streams** (the virtual campaign): :func:`stream_sequence`, :func:`stream_generator`,
  :func:`stream_seed31`. The master seed is the entropy and the keys naming the purpose
  (e.g. ``("scene", "s10_03_007")``) are the spawn key, each string key as its
  :func:`stable_hash`. A stream does not depend on the order in which other streams are
  used, on which datasets are generated, or on which effects are switched on.
- **Hashed parts** (the forward model and the stages that use it): :func:`hashed_sequence`,
  :func:`hashed_generator`, :func:`hashed_seed63`; :func:`child_seed63` and
  :func:`sequence_generator` split one such sequence into an MCRT seed and a generator. All
  parts (master seed, dataset, purpose, ids) form the entropy list, strings as their
  :func:`stable_hash`.
- **Named streams** (stage draws, the diagnosis, the bootstrap, the tracer key, the scene
  builder): :func:`named_sequence`, :func:`named_generator`, :func:`named_generators`,
  :func:`named_seeds`, :func:`named_seed`. A name of :data:`STREAMS` fixes the tag appended
  to the seed: entropy ``[seed, *tag, *keys]`` (just ``seed`` when both are empty; the same
  state). :data:`STREAMS` documents every name's purpose.

:func:`hash_ids` scrambles integer ids under a key with the SplitMix64 finaliser (per-pulse
ranks, instance and chunk assignment). Every function here is pure and process-independent.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass

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


def hashed_generator(*parts) -> np.random.Generator:
    """A PCG64 generator seeded by :func:`hashed_sequence` of ``parts``."""
    return np.random.default_rng(hashed_sequence(*parts))


def sequence_generator(ss: np.random.SeedSequence) -> np.random.Generator:
    """A PCG64 generator seeded by ``ss`` (e.g. a :func:`hashed_sequence`)."""
    return np.random.default_rng(ss)


def child_seed63(ss: np.random.SeedSequence) -> int:
    """The 63-bit seed (in [0, 2^63)) of the first child ``ss.spawn(1)[0]`` of an unspawned ``ss``.

    Pure: the child (spawn key ``ss.spawn_key + (0,)``) is built without spawning, so ``ss``
    is unchanged and a generator from ``ss`` is independent of it.
    """
    child = np.random.SeedSequence(ss.entropy, spawn_key=tuple(ss.spawn_key) + (0,), pool_size=ss.pool_size)
    return int(child.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


# -- named streams --------------------------------------------------------------------------------

@dataclass(frozen=True)
class NamedStream:
    """A named stream: the ints appended to the seed in the entropy list, and what it draws."""

    tag: tuple[int, ...]
    purpose: str


STREAMS: dict[str, NamedStream] = {
    "calibrate_extra": NamedStream((0xCFD,), "calibrate: the extra pulses read beside the target pulses"),
    "tune_cfd_pulses": NamedStream((0xCFD, 0x5E1F), "tune-cfd: the pulses the CFD is tuned on"),
    "quicklook_reservoir": NamedStream((0x91C,), "quicklook: the per-feature sample that places the histogram edges"),
    "quicklook_gallery": NamedStream((0x6A1,), "quicklook: the pulses of the waveform gallery"),
    "quicklook_scatter": NamedStream((0x9107,), "quicklook report: the pulses drawn in a scatter plot"),
    "quicklook_decomposition": NamedStream((0xDEC,), "quicklook: the pulses decomposed for the echo figures"),
    "compare_waveforms": NamedStream((), "compare: the example waveforms of Figs. 6-7 (real, then simulated)"),
    "missing_effects": NamedStream((8,), "diagnosis, 3 seeds: search, 'after' simulations, before/after bootstrap"),
    "power": NamedStream((9,), "power analysis: one seed per pseudo-real replicate"),
    "power_replicate": NamedStream((), "one power replicate's 3 seeds: its pool members per field sample (a generator), -, bootstrap"),
    "search": NamedStream((), "search, 7 seeds: split, simulations A, B, bootstrap weights A, B, gap on all, signature on all"),
    "search_split": NamedStream((), "search: the shuffle of each stratum's samples into the halves"),
    "replicate": NamedStream((), "the simulator seed of replicate r (key r) of a simulation seed"),
    "bootstrap": NamedStream((), "cluster bootstrap: the multinomial multiplicities of the samples"),
    "mcrt_key": NamedStream((), "tracer: the uint64 key of the counter-based generator"),
    "scene_build": NamedStream((), "vegetation scene, 3 spawned streams: plant, understory, LAI jitter"),
    "las_summary_z": NamedStream((), "LAS summary: the subsample of z that places the outlier bounds"),
    "survey": NamedStream((0x5EE,), "survey: the tracer key and sensor draws of one tile (key: its number)"),
}
"""Every named stream: name -> (tag, purpose). A tag is fixed forever once results depend on it."""


def _seed(seed) -> int:
    """The master seed as an int; TypeError unless an int (numpy ints included, bool excluded)."""
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed: expected an integer, got {seed!r}")
    return int(seed)


def named_sequence(name: str, seed: int, *keys: int) -> np.random.SeedSequence:
    """``SeedSequence([seed, *tag, *keys])`` of the stream ``name`` (:data:`STREAMS`).

    Raises KeyError for an unknown name, TypeError for a non-integer seed, ValueError for a
    negative one.
    """
    try:
        tag = STREAMS[name].tag
    except KeyError:
        raise KeyError(f"unknown random stream {name!r}; known: {', '.join(sorted(STREAMS))}") from None
    entropy = [_seed(seed), *tag, *(_seed(k) for k in keys)]
    return np.random.SeedSequence(entropy[0] if len(entropy) == 1 else entropy)


def named_generator(name: str, seed: int, *keys: int) -> np.random.Generator:
    """A PCG64 generator of the stream ``name`` under ``seed`` (``default_rng`` of :func:`named_sequence`)."""
    return np.random.default_rng(named_sequence(name, seed, *keys))


def named_generators(name: str, seed: int, n: int) -> list[np.random.Generator]:
    """``n`` independent generators, from the ``n`` children spawned by :func:`named_sequence`."""
    return [np.random.default_rng(child) for child in named_sequence(name, seed).spawn(int(n))]


def named_seeds(name: str, seed: int, *keys: int, n: int) -> list[int]:
    """``n`` 32-bit integer seeds (in [0, 2^32)): the state words of :func:`named_sequence`."""
    return [int(s) for s in named_sequence(name, seed, *keys).generate_state(int(n), dtype=np.uint32)]


def named_seed(name: str, seed: int, *keys: int, bits: int = 32) -> int:
    """One integer seed of 32 or 64 bits: the first state word of :func:`named_sequence`."""
    if bits not in (32, 64):
        raise ValueError(f"bits: expected 32 or 64, got {bits!r}")
    dtype = np.uint32 if bits == 32 else np.uint64
    return int(named_sequence(name, seed, *keys).generate_state(1, dtype=dtype)[0])
