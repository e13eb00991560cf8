"""Numba kernels of the wavefront tracer (docs/method.md §(d)): ray emission, one scattering order,
and the binning of receiver contributions.

Each private ``_..._kernel`` is a pure ``@njit`` function on contiguous arrays; the public
wrapper beside it checks shapes, dtypes and values. Geometry is in the internal frame of a
:class:`~waveforest.mcrt.prepare.PreparedScene` (scene coordinates minus its ``shift``).

Random numbers come from a counter-based generator: the ``k``-th uniform of ray ``i`` of
beam ``b`` at scattering order ``n`` is a SplitMix64 hash of (beam key, i, n, k), where the
beam key hashes the seed and the beam's index in the ``trace`` call. Results are therefore
identical whatever the number of threads, the chunking of beams or the order in which rays
are processed.

Samplers (``sampler``): ``0`` the pseudo-random stream above; ``1`` randomized quasi-Monte
Carlo, an Owen-scrambled Sobol' sequence (:data:`SOBOL_DIMS` dimensions, Joe & Kuo 2008
direction numbers; ray ``i`` of a beam is point ``i``). Dimensions: 0-1 the beam position,
then per scattering order n = 1, 2, ... three (branch, direction 1, direction 2) from
``2 + 3 (n - 1)``; dimensions beyond the table fall back to the pseudo-random stream. Each
dimension of each beam is scrambled independently (a hash-based nested uniform scramble,
Burley 2020 with Vegdahl's 2021 hash, then a random digital shift), seeded from the beam key:
every point is uniform on [0, 1) (the estimator stays unbiased) and the points of a beam keep
the Sobol' net's stratification.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from waveforest.constants import C_M_PER_NS, KIND_GROUND, KIND_LEAF, RAY_EPS_M
from waveforest.mcrt.threads import MIN_PARALLEL_RAYS, NumbaThreads

GOLDEN = np.uint64(0x9E3779B97F4A7C15)
"""SplitMix64 increment (2^64 / golden ratio)."""
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_TWO_M53 = 1.0 / 9007199254740992.0

DRAWS_PER_ORDER = 8
"""Uniforms reserved per ray and scattering order (counter stride)."""

SLOT_BRANCH, SLOT_LOBE, SLOT_DIR1, SLOT_DIR2 = 0, 1, 2, 3
"""Which uniform of a ray's order decides what: reflect/transmit, specular lobe, direction."""

MISS_KIND = 4
"""Code of a miss in ``first_hit_counts`` (after the element kinds 0..3)."""

SAMPLERS = {"random": 0, "sobol": 1}
"""Sampler names and their codes in the kernels (module docstring)."""

SOBOL_POLY = (1, 3, 7, 11, 13, 19, 25, 37, 41, 47, 55, 59, 61, 67, 91, 97, 103, 109, 115, 131, 137,
              143, 145, 157, 167, 171, 185, 191, 193, 203, 211, 213)
"""Primitive polynomials of the Sobol' dimensions (Joe & Kuo 2008, new-joe-kuo-6.21201; the
bits of each are its coefficients, leading and constant term included)."""

SOBOL_M = ((1,), (1,), (1, 3), (1, 3, 1), (1, 1, 1), (1, 1, 3, 3), (1, 3, 5, 13), (1, 1, 5, 5, 17),
           (1, 1, 5, 5, 5), (1, 1, 7, 11, 19), (1, 1, 5, 1, 1), (1, 1, 1, 3, 11), (1, 3, 5, 5, 31),
           (1, 3, 3, 9, 7, 49), (1, 1, 1, 15, 21, 21), (1, 3, 1, 13, 27, 49), (1, 1, 1, 15, 7, 5),
           (1, 3, 1, 15, 13, 25), (1, 1, 5, 5, 19, 61), (1, 3, 7, 11, 23, 15, 103),
           (1, 3, 7, 13, 13, 15, 69), (1, 1, 3, 13, 7, 35, 63), (1, 3, 5, 9, 1, 25, 53),
           (1, 3, 1, 13, 9, 35, 107), (1, 3, 1, 5, 27, 61, 31), (1, 1, 5, 11, 19, 41, 61),
           (1, 3, 5, 3, 3, 13, 69), (1, 1, 7, 13, 1, 19, 1), (1, 3, 7, 5, 13, 19, 59),
           (1, 1, 3, 9, 25, 29, 41), (1, 3, 5, 13, 23, 1, 55), (1, 3, 7, 3, 13, 59, 17))
"""Initial direction numbers m_1 ... m_s of each dimension (Joe & Kuo 2008)."""

SOBOL_DIMS = len(SOBOL_POLY)
"""Dimensions of the Sobol' sampler (position + 10 orders need 2 + 3 x 9 = 29)."""


def sobol_matrix(dims: int = SOBOL_DIMS, bits: int = 32) -> np.ndarray:
    """Direction numbers of the Sobol' sequence: ``v[d, j]`` is the 32-bit fraction XORed in
    when bit ``j`` of the point index is set (point ``i`` in natural, not Gray-code, order).

    Returns
    -------
    (dims, bits) uint32
        Dimension 0 is the van der Corput sequence (``v[0, j] = 2**(31 - j)``).
    """
    if not 1 <= dims <= SOBOL_DIMS or not 1 <= bits <= 32:
        raise ValueError(f"dims: expected 1..{SOBOL_DIMS}, bits 1..32")
    v = np.zeros((dims, bits), np.uint64)
    for d in range(dims):
        poly, m = SOBOL_POLY[d], list(SOBOL_M[d])
        s = poly.bit_length() - 1
        if s == 0:  # van der Corput
            m = [1] * bits
        for k in range(len(m), bits):  # Bratley & Fox recurrence
            new = m[k - s] ^ (m[k - s] << s)
            for j in range(1, s):
                if (poly >> (s - j)) & 1:
                    new ^= m[k - j] << j
            m.append(new)
        for j in range(bits):
            v[d, j] = m[j] << (31 - j)
    return v.astype(np.uint32)


def sobol_tables(v: np.ndarray) -> np.ndarray:
    """Byte tables of direction numbers ``v`` (dims, 32): ``t[d, k, b]`` is the XOR of
    ``v[d, 8 k + j]`` over the set bits j of the byte b, so that the unscrambled coordinate of
    point i is ``t[d, 0, i & 255] ^ t[d, 1, (i >> 8) & 255] ^ t[d, 2, ...] ^ t[d, 3, i >> 24]``.

    Returns
    -------
    (dims, 4, 256) uint32
    """
    dims = v.shape[0]
    t = np.zeros((dims, 4, 256), np.uint32)
    b = np.arange(256)
    for k in range(4):
        for j in range(8):
            t[:, k, :] ^= np.where(((b >> j) & 1)[None, :] == 1, v[:, 8 * k + j][:, None], 0).astype(np.uint32)
    return t


SOBOL_V = sobol_tables(sobol_matrix())
"""(SOBOL_DIMS, 4, 256) uint32 byte tables of the direction numbers, as the kernels read them."""


# --------------------------------------------------------------------------- random numbers


@njit(cache=True, inline="always")
def _mix(z):
    """SplitMix64 finaliser of a uint64."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def _stream(beam_key, ray):
    """The random stream (a uint64) of one ray of a beam."""
    return _mix(beam_key + np.uint64(ray) * GOLDEN)


@njit(cache=True, inline="always")
def _uniform(stream, order, slot):
    """Uniform in [0, 1) number ``slot`` of scattering order ``order`` of a ray's stream."""
    c = np.uint64(order * DRAWS_PER_ORDER + slot + 1)
    return np.float64(_mix(stream + c * GOLDEN) >> _S11) * _TWO_M53


_U32 = np.uint64(0xFFFFFFFF)
_TWO_M32 = 1.0 / 4294967296.0


@njit(cache=True, inline="always")
def _reverse32(x):
    """Bits 0..31 of a uint64 reversed (the result < 2**32)."""
    x = ((x >> np.uint64(1)) & np.uint64(0x55555555)) | ((x & np.uint64(0x55555555)) << np.uint64(1))
    x = ((x >> np.uint64(2)) & np.uint64(0x33333333)) | ((x & np.uint64(0x33333333)) << np.uint64(2))
    x = ((x >> np.uint64(4)) & np.uint64(0x0F0F0F0F)) | ((x & np.uint64(0x0F0F0F0F)) << np.uint64(4))
    x = ((x >> np.uint64(8)) & np.uint64(0x00FF00FF)) | ((x & np.uint64(0x00FF00FF)) << np.uint64(8))
    return ((x >> np.uint64(16)) | (x << np.uint64(16))) & _U32


@njit(cache=True, inline="always")
def _owen32(x, seed):
    """Nested uniform scramble of the 32-bit fraction ``x``: bit k is flipped by a hash of
    ``seed`` and the bits above it (Burley 2020; hash of Vegdahl 2021), then a digital shift by
    the seed's high 32 bits (every scrambled value uniform over the seeds)."""
    x = _reverse32(x)
    s = seed & _U32
    x = (x ^ (x * np.uint64(0x3D20ADEA))) & _U32
    x = (x + s) & _U32
    x = (x * ((s >> np.uint64(16)) | np.uint64(1))) & _U32
    x = (x ^ (x * np.uint64(0x05526C56))) & _U32
    x = (x ^ (x * np.uint64(0x53A22864))) & _U32
    return _reverse32(x) ^ (seed >> np.uint64(32))


@njit(cache=True, inline="always")
def _sobol_seed(beam_key, dim):
    """The scramble seed of Sobol' dimension ``dim`` of a beam."""
    return _mix(beam_key ^ (np.uint64(dim + 1) * _M2))


@njit(cache=True, inline="always")
def _sobol_scrambled(v, seed, ray, dim):
    """Uniform in (0, 1): coordinate ``dim`` of point ``ray`` scrambled with ``seed``."""
    i = np.int64(ray)
    x = np.uint64(v[dim, 0, i & 255] ^ v[dim, 1, (i >> 8) & 255] ^ v[dim, 2, (i >> 16) & 255]
                  ^ v[dim, 3, (i >> 24) & 255])
    return (np.float64(_owen32(x, seed)) + 0.5) * _TWO_M32


@njit(cache=True, inline="always")
def _sobol_uniform(v, beam_key, ray, dim):
    """Uniform in (0, 1): coordinate ``dim`` of point ``ray`` of the beam's scrambled Sobol' set."""
    return _sobol_scrambled(v, _sobol_seed(beam_key, dim), ray, dim)


@njit(cache=True, inline="always")
def _draw(sampler, v, beam_key, stream, ray, order, slot, dim):
    """Uniform of sampler ``sampler``: Sobol' dimension ``dim`` (while the table has it), else
    the pseudo-random ``slot`` of ``order``."""
    if sampler == 1 and dim < v.shape[0]:
        return _sobol_uniform(v, beam_key, ray, dim)
    return _uniform(stream, order, slot)


@njit(cache=True)
def _sobol_points_kernel(v, beam_key, n, dims, out):
    for i in range(n):
        for d in range(dims):
            out[i, d] = _sobol_uniform(v, beam_key, i, d)


def sobol_points(beam_key, n: int, dims: int = SOBOL_DIMS) -> np.ndarray:
    """The first ``n`` points of one beam's scrambled Sobol' set (the sampler ``sobol``).

    Parameters
    ----------
    beam_key : uint64
        The beam's stream key (:func:`beam_keys`).
    n, dims : int

    Returns
    -------
    (n, dims) float64 in (0, 1)
    """
    if not 1 <= dims <= SOBOL_DIMS or n < 0:
        raise ValueError(f"dims: expected 1..{SOBOL_DIMS}; n >= 0")
    out = np.empty((n, dims))
    _sobol_points_kernel(SOBOL_V, np.uint64(beam_key), int(n), int(dims), out)
    return out


@njit(cache=True)
def _beam_keys_kernel(key, index, out):
    for j in range(index.size):
        out[j] = _mix(key + np.uint64(index[j]) * GOLDEN)


def beam_keys(key: int | np.uint64, index: np.ndarray) -> np.ndarray:
    """Per-beam stream keys from a master key and the beams' indices in the trace call.

    Parameters
    ----------
    key : uint64
        Master key (derived from the seed).
    index : (nb,) int64
        Index of each beam in the ``trace`` call.

    Returns
    -------
    (nb,) uint64
    """
    idx = np.ascontiguousarray(index, dtype=np.int64)
    if idx.ndim != 1 or np.any(idx < 0):
        raise ValueError("index: expected a 1-D array of non-negative beam indices")
    out = np.empty(idx.size, np.uint64)
    _beam_keys_kernel(np.uint64(key), idx, out)
    return out


# --------------------------------------------------------------------------- geometry helpers

_HALF_PI = 0.5 * math.pi
_SIN_T = tuple((-1) ** k / math.factorial(2 * k + 1) for k in range(1, 9))
_COS_T = tuple((-1) ** k / math.factorial(2 * k) for k in range(2, 10))


@njit(cache=True, inline="always")
def _sincos_turn(u):
    """(sin 2 pi u, cos 2 pi u) for u in [0, 1].

    Exact reduction to the nearest quarter turn q (4 u - q is exact), Taylor series to degree
    17 / 18 on |x| <= pi / 4 (truncation below 1e-19), the quadrant applied by selects: within
    ~1 ulp of the exact value (libm's sin and cos of the rounded 2 pi u: ~3 ulp), about a
    third of their time and without branches.
    """
    v = 4.0 * u
    q = np.int64(v + 0.5)
    x = (v - q) * _HALF_PI
    z = x * x
    s1, s2, s3, s4, s5, s6, s7, s8 = _SIN_T
    c2, c3, c4, c5, c6, c7, c8, c9 = _COS_T
    s = x + x * z * (s1 + z * (s2 + z * (s3 + z * (s4 + z * (s5 + z * (s6 + z * (s7 + z * s8)))))))
    c = 1.0 - 0.5 * z + z * z * (c2 + z * (c3 + z * (c4 + z * (c5 + z * (c6 + z * (c7 + z * (c8 + z * c9)))))))
    swap = (q & 1) == 1  # odd quarter turns swap sine and cosine
    a = c if swap else s
    b = s if swap else c
    return (-a if q & 2 else a), (-b if (q + 1) & 2 else b)


@njit(cache=True, inline="always")
def _around(wx, wy, wz, cos_t, sin_t, phi):
    """Unit vector at polar angle (cos_t, sin_t) and azimuth ``phi`` about unit vector w.

    Orthonormal basis of Duff et al. (2017), branch-free except for the sign of w_z; the
    result is unit to rounding error.
    """
    sign = 1.0 if wz >= 0.0 else -1.0
    a = -1.0 / (sign + wz)
    b = wx * wy * a
    t1x, t1y, t1z = 1.0 + sign * wx * wx * a, sign * b, -sign * wx
    t2x, t2y, t2z = b, sign + wy * wy * a, -wy
    cp = math.cos(phi)  # sin from cos: one transcendental instead of two
    sp = math.sqrt(max(0.0, 1.0 - cp * cp))
    if phi > math.pi:
        sp = -sp
    x = sin_t * (cp * t1x + sp * t2x) + cos_t * wx
    y = sin_t * (cp * t1y + sp * t2y) + cos_t * wy
    z = sin_t * (cp * t1z + sp * t2z) + cos_t * wz
    return x, y, z


# --------------------------------------------------------------------------- data


@dataclass
class Rays:
    """Live rays of a wavefront (internal frame).

    Attributes
    ----------
    origin : (m, 3) float32, m
    direction : (m, 3) float32, unit
    power : (m,) float64
        Ray power, fraction of the pulse's emitted power.
    path_m : (m,) float64, m
        Path length from the sensor to ``origin`` (the part skipped outside the scene included).
    beam : (m,) int32
        Index of the ray's beam in the current chunk.
    ray : (m,) int32
        Index of the ray within its beam (its random-stream counter).
    """

    origin: np.ndarray
    direction: np.ndarray
    power: np.ndarray
    path_m: np.ndarray
    beam: np.ndarray
    ray: np.ndarray

    def __len__(self) -> int:
        return len(self.power)

    def take(self, index: np.ndarray) -> Rays:
        """The rays selected by an index array."""
        return Rays(self.origin[index], self.direction[index], self.power[index],
                    self.path_m[index], self.beam[index], self.ray[index])

    def head(self, m: int) -> Rays:
        """Views of the first ``m`` rays."""
        return Rays(self.origin[:m], self.direction[:m], self.power[:m], self.path_m[:m],
                    self.beam[:m], self.ray[:m])


@dataclass
class BeamFrame:
    """Per-beam constants of a chunk of beams in the internal frame.

    Attributes
    ----------
    sensor : (nb, 3) float64, m
        Sensor (= receiver) positions.
    axis : (nb, 3) float64
        Unit beam axes.
    t0_ns : (nb,) float64, ns
        Two-way time from emission of the left edge of sigma bin 0.
    key : (nb,) uint64
        Random-stream key of each beam (:func:`beam_keys`).
    """

    sensor: np.ndarray
    axis: np.ndarray
    t0_ns: np.ndarray
    key: np.ndarray

    def __len__(self) -> int:
        return len(self.key)


# --------------------------------------------------------------------------- emission


EMIT_BLOCK = 1024
"""Rays per ``prange`` task of the emission kernel (one beam's constants per task)."""


@njit(cache=True, parallel=True, nogil=True)
def _emit_kernel(sensor, axis, e1, e2, sd, range_m, plane_m, key, n_rays,
                 origin, direction, path, beam, ray, sampler, v, first_ray):
    nb = sensor.shape[0]
    per = (n_rays + EMIT_BLOCK - 1) // EMIT_BLOCK
    for task in prange(nb * per):
        b = task // per
        k0 = (task - b * per) * EMIT_BLOCK
        kb = key[b]
        seed0, seed1 = _sobol_seed(kb, 0), _sobol_seed(kb, 1)
        ax, ay, az = axis[b, 0], axis[b, 1], axis[b, 2]
        e1x, e1y, e1z = e1[b, 0], e1[b, 1], e1[b, 2]
        e2x, e2y, e2z = e2[b, 0], e2[b, 1], e2[b, 2]
        sx, sy, sz = sensor[b, 0], sensor[b, 1], sensor[b, 2]
        sdb, r, pl = sd[b], range_m[b], plane_m[b]
        for k in range(k0, min(n_rays, k0 + EMIT_BLOCK)):
            j = b * n_rays + k
            i = first_ray[b] + k
            if sampler == 1:
                u1 = _sobol_scrambled(v, seed0, i, 0)
                u2 = _sobol_scrambled(v, seed1, i, 1)
            else:
                s = _stream(kb, i)
                u1 = _uniform(s, 0, 0)
                u2 = _uniform(s, 0, 1)
            rad = math.sqrt(-2.0 * math.log(1.0 - u1)) * sdb  # Box-Muller, 1 - u1 in (0, 1]
            sin_a, cos_a = _sincos_turn(u2)
            gx, gy = rad * cos_a, rad * sin_a
            ox = gx * e1x + gy * e2x
            oy = gx * e1y + gy * e2y
            oz = gx * e1z + gy * e2z
            if r > 0.0:  # diverging: from the sensor point through the offset at range r
                dx, dy, dz = r * ax + ox, r * ay + oy, r * az + oz
                inv = 1.0 / math.sqrt(dx * dx + dy * dy + dz * dz)
                dx, dy, dz = dx * inv, dy * inv, dz * inv
                t = pl / (dx * ax + dy * ay + dz * az)
                px, py, pz = sx + t * dx, sy + t * dy, sz + t * dz
            else:  # collimated: parallel to the axis, offset at the sensor
                dx, dy, dz = ax, ay, az
                t = pl
                px, py, pz = sx + ox + t * ax, sy + oy + t * ay, sz + oz + t * az
            origin[j, 0], origin[j, 1], origin[j, 2] = px, py, pz
            direction[j, 0], direction[j, 1], direction[j, 2] = dx, dy, dz
            path[j] = t
            beam[j] = b
            ray[j] = i


def emit_rays(frame: BeamFrame, footprint_m, range_m, plane_m, n_rays: int, sampler: str = "random",
              first_ray: int = 0) -> Rays:
    """The rays of a chunk of beams, started on a plane just before the scene (docs/method.md §(d)).

    Ray offsets across the axis are Gaussian with per-axis SD ``footprint / (2 sqrt 2)``
    (irradiance exp(-(2r/d)^2), d the 1/e diameter). Each ray starts where it crosses the
    plane perpendicular to its beam's axis at distance ``plane_m`` from the sensor, and
    carries the skipped path length in float64.

    Parameters
    ----------
    frame : BeamFrame
    footprint_m : (nb,) float64, m
        1/e footprint diameters.
    range_m : (nb,) float64, m
        Range at which a diverging beam has its footprint; NaN or <= 0 = collimated.
    plane_m : (nb,) float64, m
        Distance of the start plane from the sensor along the axis, >= 0.
    n_rays : int
        Rays per beam; each carries power 1 / n_rays.
    sampler : {"random", "sobol"}
        Source of the two uniforms of each offset (Box-Muller): pseudo-random, or Sobol'
        dimensions 0 and 1 (module docstring).
    first_ray : int or (nb,) int
        Index of each beam's first ray (its random-stream counter and Sobol' point): the rays
        are points ``first_ray .. first_ray + n_rays - 1`` of the beam's sequence.

    Returns
    -------
    Rays
        ``nb * n_rays`` rays, beam-major.
    """
    nb = len(frame)
    if n_rays < 1:
        raise ValueError(f"n_rays: expected >= 1, got {n_rays}")
    # writable copies: Numba compiles a read-only array (a size-1 broadcast) as another type
    first = np.require(np.broadcast_to(np.asarray(first_ray, np.int64), (nb,)), requirements=["C", "W"])
    if nb and not (first.min() >= 0 and first.max() + n_rays <= 2**31 - 1):
        raise ValueError(f"first_ray: expected 0 <= first_ray and first_ray + n_rays < 2**31, got {first_ray}")
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler: expected one of {', '.join(SAMPLERS)}, got {sampler!r}")
    sensor = np.ascontiguousarray(frame.sensor, np.float64)
    axis = np.ascontiguousarray(frame.axis, np.float64)
    if sensor.shape != (nb, 3) or axis.shape != (nb, 3):
        raise ValueError("frame: sensor and axis must be (nb, 3)")
    fp = np.require(np.broadcast_to(np.asarray(footprint_m, np.float64), (nb,)), requirements=["C", "W"])
    rng = np.nan_to_num(np.broadcast_to(np.asarray(range_m, np.float64), (nb,)), nan=0.0)
    plane = np.require(np.broadcast_to(np.asarray(plane_m, np.float64), (nb,)), requirements=["C", "W"])
    if np.any(fp < 0) or np.any(plane < 0):
        raise ValueError("footprint_m and plane_m must be >= 0")
    if not np.allclose(np.linalg.norm(axis, axis=1), 1.0, atol=1e-9):
        raise ValueError("frame.axis: expected unit vectors")
    # an orthonormal pair across each axis
    helper = np.where(np.abs(axis[:, [2]]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    e1 = np.cross(axis, helper)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(axis, e1)
    m = nb * int(n_rays)
    origin = np.empty((m, 3), np.float32)
    direction = np.empty((m, 3), np.float32)
    path = np.empty(m, np.float64)
    beam = np.empty(m, np.int32)
    ray = np.empty(m, np.int32)
    with NumbaThreads(1 if m < MIN_PARALLEL_RAYS else None):
        _emit_kernel(sensor, axis, np.ascontiguousarray(e1), np.ascontiguousarray(e2),
                     fp / (2.0 * math.sqrt(2.0)), np.ascontiguousarray(rng), plane,
                     np.ascontiguousarray(frame.key, np.uint64), int(n_rays),
                     origin, direction, path, beam, ray, SAMPLERS[sampler], SOBOL_V, first)
    power = np.full(m, 1.0 / n_rays)
    return Rays(origin, direction, power, path, beam, ray)


# --------------------------------------------------------------------------- one order


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _scatter_kernel(order, last, org, dirs, power, path, beam, ray, tfar, prim, tri,
                    sensor, axis, t0_ns, key,
                    n_bins, bin_ns, radius2, specular, phong_n, hotspot, eps,
                    c_val, c_bin, sh_org, sh_dir, sh_t,
                    n_org, n_dir, n_power, n_path, alive, sampler, v, survive, floor_power):
    """Ray ``i`` of one order: its receiver contribution and its next ray (the contract and
    the equations: :func:`scatter`). One ``prange`` loop over the rays, in two sections:
    receiver contribution (Eq. 2) and next order (branch, roulette, direction)."""
    m = org.shape[0]
    d0 = 2 + 3 * (order - 1)  # Sobol' dimensions of this order: branch, direction 1, direction 2
    inv_pi = 1.0 / math.pi
    lobe_norm = (phong_n + 2.0) / (2.0 * math.pi)
    lobe_weight = (phong_n + 2.0) / (phong_n + 1.0)
    inv_c = 1.0 / C_M_PER_NS
    inv_bin = 1.0 / bin_ns
    for i in prange(m):
        c_val[i] = 0.0
        c_bin[i] = -1
        sh_t[i] = 0.0
        alive[i] = False
        p = prim[i]
        if p < 0:
            continue  # escaped
        b = beam[i]
        nx, ny, nz = tri[p, 0], tri[p, 1], tri[p, 2]
        if nx == 0.0 and ny == 0.0 and nz == 0.0:
            continue  # degenerate triangle: absorb
        t = np.float64(tfar[i])
        dx, dy, dz = np.float64(dirs[i, 0]), np.float64(dirs[i, 1]), np.float64(dirs[i, 2])
        x = np.float64(org[i, 0]) + t * dx
        y = np.float64(org[i, 1]) + t * dy
        z = np.float64(org[i, 2]) + t * dz
        cos_in = dx * nx + dy * ny + dz * nz
        if cos_in > 0.0:  # s = normal on the illuminated side
            sx, sy, sz = -nx, -ny, -nz
        else:
            sx, sy, sz = nx, ny, nz
        r = tri[p, 3]
        tr = tri[p, 4]
        k = np.int64(tri[p, 5])
        length = path[i] + t
        # mirror direction of the incoming ray (specular lobe)
        mx = dx - 2.0 * cos_in * nx
        my = dy - 2.0 * cos_in * ny
        mz = dz - 2.0 * cos_in * nz
        spec = specular if k == KIND_LEAF else 0.0

        # ---- receiver contribution (Eq. 2), only inside the viewed cylinder
        vx, vy, vz = sensor[b, 0] - x, sensor[b, 1] - y, sensor[b, 2] - z
        along = -(vx * axis[b, 0] + vy * axis[b, 1] + vz * axis[b, 2])
        px, py, pz = -vx - along * axis[b, 0], -vy - along * axis[b, 1], -vz - along * axis[b, 2]
        if px * px + py * py + pz * pz <= radius2:
            dist = math.sqrt(vx * vx + vy * vy + vz * vz)
            wx, wy, wz = vx / dist, vy / dist, vz / dist
            cr = wx * sx + wy * sy + wz * sz
            side = 1.0
            if order == 1:  # monostatic: the path back is the path in, always the lit side
                cr = abs(cr)
                total = 2.0 * length
            else:
                total = length + dist
            if cr >= 0.0:
                brdf = r * inv_pi
                if spec > 0.0:
                    ca = wx * mx + wy * my + wz * mz
                    lobe = ca ** phong_n if ca > 0.0 else 0.0
                    brdf = (1.0 - spec) * r * inv_pi + spec * r * lobe_norm * lobe
                coef = brdf * cr
            else:  # receiver on the far side: diffuse transmission
                coef = tr * inv_pi * (-cr)
                side = -1.0
            if order == 1 and k != KIND_GROUND:
                coef *= hotspot
            val = power[i] * coef
            if val > 0.0:
                c_val[i] = val
                tb = (total * inv_c - t0_ns[b]) * inv_bin
                if tb >= 0.0 and tb < n_bins:
                    c_bin[i] = np.int64(tb)
                if order > 1:  # visibility ray towards the receiver
                    sh_org[i, 0] = x + side * eps * sx
                    sh_org[i, 1] = y + side * eps * sy
                    sh_org[i, 2] = z + side * eps * sz
                    sh_dir[i, 0], sh_dir[i, 1], sh_dir[i, 2] = wx, wy, wz
                    sh_t[i] = dist

        # ---- next order: reflect with probability rho / (rho + tau), else transmit
        if last or r + tr <= 0.0:
            continue
        s = _stream(key[b], ray[i])
        weight = r + tr
        ub = _draw(sampler, v, key[b], s, ray[i], order, SLOT_BRANCH, d0)
        q = survive[order]
        if floor_power > 0.0 and power[i] * weight < floor_power:  # weight window
            q *= power[i] * weight / floor_power
        if q < 1.0:  # Russian roulette: continue with probability q, weight 1 / q
            if ub >= q:
                continue
            ub = ub / q  # uniform on [0, 1) again, for the branch
            weight = weight / q
        u = _draw(sampler, v, key[b], s, ray[i], order, SLOT_DIR1, d0 + 1)
        phi = 2.0 * math.pi * _draw(sampler, v, key[b], s, ray[i], order, SLOT_DIR2, d0 + 2)
        if ub * (r + tr) < r:
            ox, oy, oz = sx, sy, sz
            lobe_u = 1.0
            if spec > 0.0:  # random: its own uniform; sobol: the branch uniform rescaled
                lobe_u = _uniform(s, order, SLOT_LOBE) if sampler == 0 else ub * (r + tr) / r
            if lobe_u < spec:
                # Phong lobe about the mirror direction, pdf (n+1)/(2 pi) cos^n(alpha)
                ca = u ** (1.0 / (phong_n + 1.0))
                sa = math.sqrt(max(0.0, 1.0 - ca * ca))
                ex, ey, ez = _around(mx, my, mz, ca, sa, phi)
                cos_o = ex * sx + ey * sy + ez * sz
                if cos_o <= 0.0:
                    continue  # below the surface: the lobe's energy loss at oblique incidence
                weight *= lobe_weight * cos_o
            else:
                ex, ey, ez = _around(ox, oy, oz, math.sqrt(1.0 - u), math.sqrt(u), phi)
        else:
            ox, oy, oz = -sx, -sy, -sz
            ex, ey, ez = _around(ox, oy, oz, math.sqrt(1.0 - u), math.sqrt(u), phi)
        n_org[i, 0] = x + eps * ox
        n_org[i, 1] = y + eps * oy
        n_org[i, 2] = z + eps * oz
        n_dir[i, 0], n_dir[i, 1], n_dir[i, 2] = ex, ey, ez
        n_power[i] = power[i] * weight
        n_path[i] = length
        alive[i] = True


@dataclass
class Scattered:
    """Result of one scattering order for every input ray (also reusable output buffers).

    Attributes
    ----------
    value : (m,) float64
        Receiver contribution (fraction of emitted power per sr); 0 = none.
    bin : (m,) int64
        sigma bin of the contribution; -1 = outside the window (counted as dropped).
    shadow_origin, shadow_direction : (m, 3) float32
        Visibility ray towards the receiver (orders >= 2, where ``value > 0``).
    shadow_tmax : (m,) float32, m
        Its length (distance to the receiver).
    origin, direction : (m, 3) float32
        Scattered rays of the next order (valid where ``alive``).
    power, path_m : (m,) float64
    alive : (m,) bool
    """

    value: np.ndarray
    bin: np.ndarray
    shadow_origin: np.ndarray
    shadow_direction: np.ndarray
    shadow_tmax: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    power: np.ndarray
    path_m: np.ndarray
    alive: np.ndarray

    @classmethod
    def empty(cls, m: int) -> Scattered:
        """Buffers for ``m`` rays."""
        return cls(np.empty(m), np.empty(m, np.int64), np.empty((m, 3), np.float32),
                   np.empty((m, 3), np.float32), np.empty(m, np.float32),
                   np.empty((m, 3), np.float32), np.empty((m, 3), np.float32),
                   np.empty(m), np.empty(m), np.empty(m, np.bool_))

    def __len__(self) -> int:
        return len(self.value)

    def head(self, m: int) -> Scattered:
        """Views of the first ``m`` entries."""
        return Scattered(*(getattr(self, f)[:m] for f in self.__dataclass_fields__))


def scatter(order: int, last: bool, rays: Rays, tfar: np.ndarray, prim: np.ndarray, prepared,
            frame: BeamFrame, n_bins: int, bin_ns: float, viewed_diameter_m: float,
            specular: float = 0.0, phong_n: float = 40.0, hotspot: float = 1.0,
            eps: float = RAY_EPS_M, out: Scattered | None = None, sampler: str = "random",
            survive: np.ndarray | None = None, floor_power: float = 0.0) -> Scattered:
    """One scattering order of a wavefront: contributions, binning and new rays (docs/method.md §(d)).

    For each ray that hit triangle ``prim`` at distance ``tfar``:

    * receiver contribution (Eq. 2) ``BRDF * cos(theta) * P`` with theta between the
      element normal and the direction to the receiver, BRDF = rho / pi on the lit side and
      tau / pi on the far side (orders >= 2; order 1 is always the lit side in a monostatic
      system), times ``hotspot`` for order-1 vegetation (kind != 0). Leaves (kind 1) with
      ``specular = s > 0`` reflect with BRDF (1 - s) rho / pi + s rho (n + 2) / (2 pi)
      cos^n(alpha), alpha between the receiver direction and the mirror direction;
      counted only if the hit lies within ``viewed_diameter_m / 2`` of the beam axis
      (perpendicular distance); binned by total path sensor -> hits -> receiver (order 1:
      twice the path in);
    * next ray: reflect with probability rho / (rho + tau) (cosine-weighted on the lit
      side; for specular leaves the Phong lobe with probability s, weight
      (n + 2) / (n + 1) cos(theta_out)), else transmit (cosine-weighted on the far side);
      power times (rho + tau); origin offset by ``eps`` along the normal on the outgoing
      side. No new rays when ``last``. With ``survive[order] = q < 1`` (Russian roulette) a
      ray continues with probability q and its power is divided by q: the branch uniform u
      decides (u < q continues; u / q then chooses the branch). With ``floor_power`` > 0
      a ray whose next power would fall below it continues with the further probability
      power / floor_power (so its power after the roulette is ``floor_power``).

    Parameters
    ----------
    order : int
        Scattering order of these hits, >= 1.
    last : bool
        True at the highest order (no new rays).
    rays : Rays
    tfar : (m,) float32, m
    prim : (m,) int32
        Triangle hit, -1 = miss.
    prepared : PreparedScene
    frame : BeamFrame
    n_bins : int
    bin_ns, viewed_diameter_m, specular, phong_n, hotspot, eps : float
    out : Scattered, optional
        Buffers of at least ``m`` rays to write into (avoids allocation per order).
    sampler : {"random", "sobol"}
        Source of the branch and direction uniforms (module docstring).
    survive : (> order,) float64, optional
        Probability in (0, 1] that a ray scattered at order n continues, at index n
        (default: 1, no roulette).
    floor_power : float
        Power floor of the roulette, fraction of the pulse's power (0 = off).

    Returns
    -------
    Scattered
        ``m`` entries (views of ``out`` if given).
    """
    m = len(rays)
    if order < 1:
        raise ValueError(f"order: expected >= 1, got {order}")
    if tfar.shape != (m,) or prim.shape != (m,) or tfar.dtype != np.float32 or prim.dtype != np.int32:
        raise ValueError(f"tfar, prim: expected float32 and int32 of shape ({m},)")
    if rays.origin.dtype != np.float32 or rays.direction.dtype != np.float32:
        raise ValueError("rays: origin and direction must be float32")
    if n_bins < 1 or bin_ns <= 0 or viewed_diameter_m <= 0:
        raise ValueError("n_bins, bin_ns and viewed_diameter_m must be positive")
    if not 0.0 <= specular <= 1.0 or hotspot < 0 or phong_n < 0:
        raise ValueError("specular must be in [0, 1], hotspot and phong_n >= 0")
    tri = prepared.tri_data
    if tri.ndim != 2 or tri.shape[1] < 6 or not tri.flags.c_contiguous:
        raise ValueError("prepared.tri_data: expected a C-contiguous (n, >= 6) float64 array")
    if m and prim.max() >= len(tri):
        raise ValueError(f"prim: index {prim.max()} out of range for {len(tri)} triangles")
    if m and (rays.beam.min() < 0 or rays.beam.max() >= len(frame)):
        raise ValueError("rays.beam: index out of range of the beam frame")
    if out is None:
        out = Scattered.empty(m)
    elif len(out) < m:
        raise ValueError(f"out: buffers for {len(out)} rays, need {m}")
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler: expected one of {', '.join(SAMPLERS)}, got {sampler!r}")
    if not (np.isfinite(floor_power) and floor_power >= 0):
        raise ValueError(f"floor_power: expected >= 0, got {floor_power!r}")
    survive = np.ones(order + 1) if survive is None else np.ascontiguousarray(survive, np.float64)
    if survive.ndim != 1 or survive.size <= order or np.any(~(survive > 0)) or np.any(survive > 1):
        raise ValueError(f"survive: expected probabilities in (0, 1] for orders 0..{order} at least")
    o = out.head(m)
    with NumbaThreads(1 if m < MIN_PARALLEL_RAYS else None):
        _scatter(order, last, rays, tfar, prim, tri, frame, n_bins, bin_ns, viewed_diameter_m, specular,
                 phong_n, hotspot, eps, o, SAMPLERS[sampler], survive, float(floor_power))
    return o


def _scatter(order, last, rays, tfar, prim, tri, frame, n_bins, bin_ns, viewed_diameter_m, specular,
             phong_n, hotspot, eps, o, sampler=0, survive=None, floor_power=0.0):
    """Call :func:`_scatter_kernel` on validated inputs (``o``: the output views; ``sampler``
    a code of :data:`SAMPLERS`)."""
    if survive is None:
        survive = np.ones(order + 1)
    _scatter_kernel(int(order), bool(last), rays.origin, rays.direction, rays.power, rays.path_m,
                    rays.beam, rays.ray, tfar, prim, tri,
                    frame.sensor, frame.axis, frame.t0_ns, frame.key,
                    int(n_bins), float(bin_ns), (0.5 * viewed_diameter_m) ** 2,
                    float(specular), float(phong_n), float(hotspot), float(eps),
                    o.value, o.bin, o.shadow_origin, o.shadow_direction, o.shadow_tmax,
                    o.origin, o.direction, o.power, o.path_m, o.alive, sampler, SOBOL_V, survive,
                    float(floor_power))


@njit(cache=True, nogil=True)
def _compact_kernel(alive, org, dirs, power, path, beam, ray,
                    d_org, d_dir, d_power, d_path, d_beam, d_ray):
    k = 0
    for i in range(alive.size):
        if alive[i]:
            d_org[k, 0], d_org[k, 1], d_org[k, 2] = org[i, 0], org[i, 1], org[i, 2]
            d_dir[k, 0], d_dir[k, 1], d_dir[k, 2] = dirs[i, 0], dirs[i, 1], dirs[i, 2]
            d_power[k] = power[i]
            d_path[k] = path[i]
            d_beam[k] = beam[i]  # in place is safe: k <= i
            d_ray[k] = ray[i]
            k += 1
    return k


def compact(scattered: Scattered, rays: Rays, dest: Rays) -> Rays:
    """The next order's live rays, packed to the front of ``dest`` (order kept).

    Parameters
    ----------
    scattered : Scattered
        Output of :func:`scatter` for ``rays`` (new origins, directions, powers, paths).
    rays : Rays
        The rays that were scattered (their beam and ray indices are carried over).
    dest : Rays
        Buffers of at least ``len(rays)`` rays; may be the buffers ``rays`` views.

    Returns
    -------
    Rays
        Views of the first k entries of ``dest``.
    """
    m = len(rays)
    if len(scattered) != m or len(dest) < m:
        raise ValueError("compact: scattered must match rays, dest must hold them")
    k = _compact_kernel(scattered.alive, scattered.origin, scattered.direction, scattered.power,
                        scattered.path_m, rays.beam, rays.ray, dest.origin, dest.direction,
                        dest.power, dest.path_m, dest.beam, dest.ray)
    return dest.head(k)


# --------------------------------------------------------------------------- binning


@njit(cache=True, nogil=True)
def _accumulate_kernel(index, beam, value, bins, layer, order, acc, dropped, totals):
    for j in range(index.size):
        i = index[j]
        b = beam[i]
        v = value[i]
        totals[b, order - 1] += v
        k = bins[i]
        if k >= 0:
            acc[b, layer, k] += v
        else:
            dropped[b] += v


def accumulate(index: np.ndarray, beam: np.ndarray, value: np.ndarray, bins: np.ndarray,
               order: int, acc: np.ndarray, dropped: np.ndarray, totals: np.ndarray,
               by_order: bool) -> None:
    """Add the contributions ``index`` into sigma (serial, so no races), in place.

    Parameters
    ----------
    index : (k,) int64
        Rays whose contribution counts (visible from the receiver).
    beam : (m,) int32
    value : (m,) float64
    bins : (m,) int64
        sigma bin, -1 = outside the window (added to ``dropped``).
    order : int
    acc : (nb, n_layers, n_bins) float64
        sigma per beam (one layer, or one layer per order when ``by_order``).
    dropped : (nb,) float64
    totals : (nb, max_order) float64
    by_order : bool
    """
    idx = np.ascontiguousarray(index, np.int64)
    if acc.ndim != 3 or dropped.shape != acc.shape[:1] or totals.shape[0] != acc.shape[0]:
        raise ValueError("acc, dropped, totals: inconsistent shapes")
    if not 1 <= order <= totals.shape[1]:
        raise ValueError(f"order: expected 1..{totals.shape[1]}, got {order}")
    layer = order - 1 if by_order else 0
    if layer >= acc.shape[1]:
        raise ValueError("acc: too few layers for by_order")
    if idx.size and (idx.min() < 0 or idx.max() >= len(value)):
        raise ValueError("index: out of range")
    if np.any(bins[idx] >= acc.shape[2]):
        raise ValueError("bins: index beyond the sigma window")
    _accumulate_kernel(idx, beam, value, bins, layer, order, acc, dropped, totals)


@njit(cache=True, nogil=True)
def _first_hits_kernel(beam, prim, tri, counts):
    for i in range(prim.size):
        p = prim[i]
        counts[beam[i], MISS_KIND if p < 0 else np.int64(tri[p, 5])] += 1


def first_hits(beam: np.ndarray, prim: np.ndarray, tri_data: np.ndarray, nb: int) -> np.ndarray:
    """(nb, MISS_KIND + 1) int64: the rays of each beam whose first hit ``prim`` (-1: miss) is
    of each element kind (``tri_data[:, 5]``), misses in the last column."""
    counts = np.zeros((nb, MISS_KIND + 1), np.int64)
    _first_hits_kernel(beam, prim, tri_data, counts)
    return counts


@njit(cache=True, parallel=True, nogil=True)
def take_rays(org, dirs, index):
    """Rows ``index`` of a ray batch's origins and directions, as new contiguous arrays.

    The same as ``org[index], dirs[index]`` (a parallel Numba gather; NumPy's fancy indexing
    of (m, 3) rows is slower, docs/validation.md, "Speed").
    """
    m = index.size
    o = np.empty((m, 3), org.dtype)
    d = np.empty((m, 3), dirs.dtype)
    for i in prange(m):
        j = index[i]
        o[i, 0], o[i, 1], o[i, 2] = org[j, 0], org[j, 1], org[j, 2]
        d[i, 0], d[i, 1], d[i, 2] = dirs[j, 0], dirs[j, 1], dirs[j, 2]
    return o, d
