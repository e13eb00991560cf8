"""The waveform gather kernel against its slow reference (tests/reference_io.py)."""

import numpy as np
import pytest
from reference_io import reference_gather

from waveforest.io.las.gather import gather_samples


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gather_matches_reference_on_random_packets(seed):
    rng = np.random.default_rng(seed)
    buf = rng.integers(0, 256, 5000, dtype=np.uint8)
    n = 60
    sample_bytes = rng.choice([1, 2, 4], n)
    n_samples = rng.integers(0, 40, n)
    byte_offset = np.array([rng.integers(0, 5000 - ns * b + 1) for ns, b in zip(n_samples, sample_bytes)])
    got, got_off = gather_samples(buf, byte_offset, n_samples, sample_bytes)
    want, want_off = reference_gather(buf, byte_offset, n_samples, sample_bytes)
    np.testing.assert_array_equal(got_off, want_off)
    np.testing.assert_array_equal(got, want)


def test_gather_known_little_endian_values():
    buf = np.array([1, 2, 3, 4, 0xFF, 0xFF, 0x34, 0x12, 0, 0, 0, 0x80], dtype=np.uint8)
    got, off = gather_samples(buf, [0, 4, 6, 8], [2, 1, 1, 1], [1, 2, 2, 4])
    np.testing.assert_array_equal(off, [0, 2, 3, 4, 5])
    np.testing.assert_array_equal(got, np.array([1, 2, 65535, 0x1234, 2.0**31], dtype=np.float32))


def test_gather_empty_and_zero_length():
    buf = np.zeros(4, np.uint8)
    got, off = gather_samples(buf, np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64))
    assert got.size == 0 and off.tolist() == [0]
    got, off = gather_samples(buf, [4], [0], [2])  # an empty packet at the very end is fine
    assert got.size == 0 and off.tolist() == [0, 0]


@pytest.mark.parametrize(
    "args, match",
    [
        ((np.zeros(10, np.uint8), [8], [2], [2]), "beyond the buffer"),
        ((np.zeros(10, np.uint8), [0], [2], [3]), "sample_bytes"),
        ((np.zeros(10, np.uint8), [-1], [2], [1]), ">= 0"),
        ((np.zeros(10, np.int16), [0], [2], [1]), "uint8"),
        ((np.zeros(10, np.uint8), [0, 1], [2], [1]), "one length"),
    ],
)
def test_gather_rejects_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        gather_samples(*args)
