"""Seed derivation: every stream of waveforest.rng equals the derivation it replaced, and no other
module derives a seed."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import waveforest
from waveforest import rng

SEEDS = [0, 1, 42, 2**31 - 1, 2**32 + 5, 2**63 - 1]


def _same(a: np.random.Generator, b: np.random.Generator) -> bool:
    """Same bit-generator state and the same next draws."""
    if a.bit_generator.state != b.bit_generator.state:
        return False
    return np.array_equal(a.integers(0, 2**63, 16), b.integers(0, 2**63, 16))


# Each named stream next to the expression it replaced (the reference, written out in full).
GENERATORS = {
    "calibrate_extra": lambda s: np.random.default_rng([int(s), 0xCFD]),
    "tune_cfd_pulses": lambda s: np.random.default_rng([int(s), 0xCFD, 0x5E1F]),
    "quicklook_reservoir": lambda s: np.random.default_rng([int(s), 0x91C]),
    "quicklook_gallery": lambda s: np.random.default_rng([int(s), 0x6A1]),
    "quicklook_scatter": lambda s: np.random.default_rng([int(s), 0x9107]),
    "quicklook_decomposition": lambda s: np.random.default_rng([int(s), 0xDEC]),
    "compare_waveforms": lambda s: np.random.default_rng(int(s)),
    "search_split": lambda s: np.random.default_rng(s),
    "bootstrap": lambda s: np.random.default_rng(s),
    "las_summary_z": lambda s: np.random.default_rng(s),
    "survey": lambda s: np.random.default_rng([int(s), 0x5EE]),
}

SEED_LISTS = {
    "missing_effects": (3, lambda s, n: np.random.SeedSequence([int(s), 8]).generate_state(n)),
    "power": (7, lambda s, n: np.random.SeedSequence([int(s), 9]).generate_state(n)),
    "power_replicate": (3, lambda s, n: np.random.SeedSequence(s).generate_state(n)),
    "search": (6, lambda s, n: np.random.SeedSequence(s).generate_state(n)),
}


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("name", sorted(GENERATORS))
def test_named_generator_matches_reference(name, seed):
    assert _same(rng.named_generator(name, seed), GENERATORS[name](seed))


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("name", sorted(SEED_LISTS))
def test_named_seeds_match_reference(name, seed):
    n, ref = SEED_LISTS[name]
    got = rng.named_seeds(name, seed, n=n)
    assert got == [int(v) for v in ref(seed, n)]
    assert all(type(v) is int for v in got)


@pytest.mark.parametrize("seed", SEEDS)
def test_numpy_integer_seeds(seed):
    """Seeds drawn as numpy words (uint32 from generate_state) seed like the int."""
    s = np.uint32(seed % 2**32)
    assert _same(rng.named_generator("bootstrap", s), np.random.default_rng(s))
    assert _same(rng.named_generator("search_split", s), np.random.default_rng(s))


@pytest.mark.parametrize("seed", SEEDS)
def test_replicate_seed(seed):
    for r in range(4):
        ref = int(np.random.SeedSequence([seed, r]).generate_state(1)[0])
        assert rng.named_seed("replicate", seed, r) == ref


@pytest.mark.parametrize("seed", SEEDS)
def test_mcrt_key(seed):
    ref = np.random.SeedSequence(int(seed)).generate_state(1, dtype=np.uint64)[0]
    assert np.uint64(rng.named_seed("mcrt_key", seed, bits=64)) == ref


@pytest.mark.parametrize("seed", SEEDS)
def test_scene_build_streams(seed):
    got = rng.named_generators("scene_build", seed, 3)
    ref = [np.random.default_rng(c) for c in np.random.SeedSequence(int(seed)).spawn(3)]
    assert len(got) == 3
    assert all(_same(a, b) for a, b in zip(got, ref))


@pytest.mark.parametrize("seed", SEEDS)
def test_hashed_generator_and_child_seed(seed):
    parts = (seed, "s10", "pulses", "s10_03_007", 3)
    assert _same(rng.hashed_generator(*parts), np.random.default_rng(rng.hashed_sequence(*parts)))
    assert _same(rng.hashed_generator(seed, "sensitivity", "geometry"),
                 np.random.default_rng(rng.hashed_sequence(seed, "sensitivity", "geometry")))
    # The forward model's group stream: first child's 63-bit MCRT seed, then the sequence itself.
    old = rng.hashed_sequence(*parts)
    old_seed = int(old.spawn(1)[0].generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))
    old_rng = np.random.default_rng(old)
    new = rng.hashed_sequence(*parts)
    assert rng.child_seed63(new) == old_seed
    assert rng.child_seed63(new) == old_seed  # pure: ss is not spawned
    assert _same(rng.sequence_generator(new), old_rng)
    # A 63-bit seed of the sequence itself (sensitivity's trace seed) is hashed_seed63.
    ss = rng.hashed_sequence(seed, "sensitivity", "pulses", 2)
    assert rng.hashed_seed63(seed, "sensitivity", "pulses", 2) == int(
        ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


def test_every_stream_is_tested():
    tested = set(GENERATORS) | set(SEED_LISTS) | {"replicate", "mcrt_key", "scene_build"}
    assert tested == set(rng.STREAMS)


def test_tags_are_distinct_where_seeded_alike():
    tags = [s.tag for s in rng.STREAMS.values() if s.tag]
    assert len(tags) == len(set(tags))


def test_bad_names_and_seeds():
    with pytest.raises(KeyError, match="unknown random stream"):
        rng.named_generator("no_such_stream", 1)
    for bad in (None, 1.5, "3", True):
        with pytest.raises(TypeError):
            rng.named_generator("bootstrap", bad)
    with pytest.raises(ValueError):
        rng.named_generator("bootstrap", -1)
    with pytest.raises(ValueError):
        rng.named_seed("replicate", 1, 0, bits=16)


# -- no other module derives a seed ---------------------------------------------------------------

FORBIDDEN = {"SeedSequence", "default_rng", "Generator", "PCG64", "PCG64DXSM", "MT19937", "Philox", "SFC64",
             "RandomState", "BitGenerator", "spawn", "generate_state"}


def _derivations(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    hits = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if name in FORBIDDEN:
                hits.append(f"{path}:{node.lineno}: {name}(")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("numpy.random"):
            hits.append(f"{path}:{node.lineno}: from {node.module} import")
    return hits


def test_no_seed_derivation_outside_rng():
    root = Path(waveforest.__file__).parent
    own = root / "rng.py"
    hits = [h for p in sorted(root.rglob("*.py")) if p != own for h in _derivations(p)]
    assert not hits, "seed derivation outside waveforest/rng.py:\n" + "\n".join(hits)
