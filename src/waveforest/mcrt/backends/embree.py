"""Embree 4 called directly from Numba kernels (the library embreex ships), docs/method.md §(d).

embreex's ``EmbreeScene.run`` traces a batch of rays one ``rtcIntersect1`` at a time from a
Cython loop, on a BVH of MEDIUM build quality it gives no way to change. Here the same Embree
library is driven through its C API: the scene is built with ctypes (build quality chosen by
the caller; consecutive triangles that share an edge as one quad, :func:`_pair_quads`), and
the per-ray ``rtcIntersect1`` / ``rtcOccluded1`` calls are made from one
``@njit(parallel=True, nogil=True)`` kernel over blocks of rays (``prange``, no Python
threads, no GIL). Each call traces sorted copies of its rays, in Z-order of their origins
(:func:`coherent_order`), and puts the results back in the caller's order (a nearest-hit call
on rays already coherent, ``coherent=True``, traces them as given); the hits are those of
embreex's ``run``. Speed against embreex and of the ray order: docs/validation.md, "Speed"
(``benchmarks/mcrt.py``).

The library is the ``libembree4`` bundled with the installed embreex wheel
(``embreex.libs``), else one found by :func:`ctypes.util.find_library`; :func:`available`
says whether it loaded. Numba links the kernels against its symbols by name
(``llvmlite.binding.load_library_permanently``), so they are cached like any other kernel.

Structure layouts (embree4/rtcore_ray.h, x86-64): ``RTCRay`` = org_x, org_y, org_z, tnear,
dir_x, dir_y, dir_z, time, tfar (float32), mask, id, flags (uint32): 48 bytes;
``RTCRayHit`` = ``RTCRay`` + ``RTCHit`` (Ng_x, Ng_y, Ng_z, u, v, primID, geomID, instID...),
16-byte aligned. Each block of rays uses one 128-byte slot (its float32 and uint32 views).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import os
import threading

import llvmlite.binding as llvm
import numba
import numpy as np
from numba import njit, prange, types

try:  # the library embreex ships
    import embreex
except ImportError:  # pragma: no cover - embreex is a dependency
    embreex = None

from waveforest.mcrt.backends.base import RayQueries, check_triangles
from waveforest.mcrt.kernels import take_rays
from waveforest.mcrt.threads import MIN_PARALLEL_RAYS, NumbaThreads

QUALITIES = {"low": 0, "medium": 1, "high": 2}
"""Embree BVH build qualities (RTC_BUILD_QUALITY_*)."""

DEFAULT_QUALITY = "high"
"""BVH quality of :func:`waveforest.mcrt.prepare`: a HIGH build is slower than a MEDIUM one
and its queries faster, so it pays for a scene traced often (:func:`waveforest.mcrt.trace` of
an unprepared scene chooses, :func:`waveforest.mcrt.tracer.bvh_quality`; the trade-off
measured: docs/validation.md, "Speed")."""

BLOCK_RAYS = 512
"""Rays per ``prange`` task (one RTCRayHit slot each)."""

CELL_BITS = 5
"""Rays are traced in Z-order of their origins on a ``2**CELL_BITS``-per-axis grid
(:func:`coherent_order`)."""

SLOT_FLOATS = 32
"""Slot size in float32 (128 bytes, room for an RTCRayHit of 96 bytes)."""

_RTC_GEOMETRY_TYPE_QUAD, _RTC_GEOMETRY_TYPE_INSTANCE = 1, 121
_RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR = 0x9234
_RTC_BUFFER_TYPE_INDEX, _RTC_BUFFER_TYPE_VERTEX = 0, 1
_RTC_FORMAT_UINT4, _RTC_FORMAT_FLOAT3 = 0x5004, 0x9003
_INVALID_ID = 0xFFFFFFFF

# RTCRayHit field offsets in float32 / uint32 units
_ORG, _TNEAR, _DIR, _TIME, _TFAR, _MASK, _ID, _FLAGS = 0, 3, 4, 7, 8, 9, 10, 11
_U, _V, _PRIM, _GEOM, _INST = 15, 16, 17, 18, 19
_NO_PRIM = np.empty(0, np.int32)
"""The ``prim`` argument of an occlusion query (not written)."""

_LIB = None
_DEVICE = None
_LOCK = threading.Lock()
_ERROR: str | None = None


def _library_path() -> str | None:
    if embreex is not None:
        site = os.path.dirname(os.path.dirname(os.path.abspath(embreex.__file__)))
        found = sorted(glob.glob(os.path.join(site, "embreex.libs", "libembree4*.so*")))
        if found:
            return found[0]
    return ctypes.util.find_library("embree4")


def _load():
    """Load libembree4 (once): ctypes handle for the build calls, symbols for Numba."""
    global _LIB, _DEVICE, _ERROR
    with _LOCK:
        if _LIB is not None or _ERROR is not None:
            return _LIB
        path = _library_path()
        if path is None:
            _ERROR = "libembree4 not found (neither in embreex.libs nor on the library path)"
            return None
        try:
            lib = ctypes.CDLL(path)
            llvm.load_library_permanently(path)
        except OSError as exc:
            _ERROR = f"libembree4 could not be loaded: {exc}"
            return None
        p = ctypes.c_void_p
        for name, res, args in (
            ("rtcNewDevice", p, [ctypes.c_char_p]),
            ("rtcGetDeviceError", ctypes.c_int, [p]),
            ("rtcNewScene", p, [p]),
            ("rtcSetSceneBuildQuality", None, [p, ctypes.c_int]),
            ("rtcNewGeometry", p, [p, ctypes.c_int]),
            ("rtcSetGeometryBuildQuality", None, [p, ctypes.c_int]),
            ("rtcSetNewGeometryBuffer", p, [p, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t,
                                            ctypes.c_size_t]),
            ("rtcCommitGeometry", None, [p]),
            ("rtcAttachGeometry", ctypes.c_uint, [p, p]),
            ("rtcReleaseGeometry", None, [p]),
            ("rtcCommitScene", None, [p]),
            ("rtcReleaseScene", None, [p]),
            ("rtcSetGeometryInstancedScene", None, [p, p]),
            ("rtcSetGeometryTransform", None, [p, ctypes.c_uint, ctypes.c_int, p]),
        ):
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = res, args
        global _rtc_intersect1, _rtc_occluded1
        if numba.config.DISABLE_JIT:  # kernels run as Python: call Embree through ctypes
            proto = ctypes.CFUNCTYPE(None, ctypes.c_size_t, ctypes.c_size_t, ctypes.c_size_t)
            _rtc_intersect1 = proto(("rtcIntersect1", lib))
            _rtc_occluded1 = proto(("rtcOccluded1", lib))
        device = lib.rtcNewDevice(None)
        if not device:
            _ERROR = f"rtcNewDevice failed (error {lib.rtcGetDeviceError(None)})"
            return None
        _LIB, _DEVICE = lib, device
        return lib


def available() -> bool:
    """True if libembree4 could be loaded for direct calls."""
    return _load() is not None


def unavailable_reason() -> str | None:
    """Why :func:`available` is False (None when it is True)."""
    _load()
    return _ERROR


_rtc_intersect1 = types.ExternalFunction("rtcIntersect1", types.void(types.uintp, types.uintp, types.uintp))
_rtc_occluded1 = types.ExternalFunction("rtcOccluded1", types.void(types.uintp, types.uintp, types.uintp))


@njit(cache=True, nogil=True, inline="always")
def _set_ray(f, u, org, dirs, i, tfar):
    """Write ray ``i`` (t from 0 to ``tfar``) into an RTCRay slot (float32 view ``f``, uint32 ``u``)."""
    f[0], f[1], f[2], f[_TNEAR] = org[i, 0], org[i, 1], org[i, 2], 0.0
    f[4], f[5], f[6], f[_TIME] = dirs[i, 0], dirs[i, 1], dirs[i, 2], 0.0
    f[_TFAR] = tfar
    u[_MASK], u[_ID], u[_FLAGS] = _INVALID_ID, 0, 0


@njit(cache=True, parallel=True, nogil=True)
def _query_kernel(scene, org, dirs, t, prim, occlusion, slot_f, slot_u, offsets, quad_base, tri_of):
    """Trace ray ``i`` from ``t = 0`` to ``t[i]`` for every ``i``, in blocks of ``BLOCK_RAYS``.

    Nearest hit (``occlusion`` False): ``t[i]`` becomes the hit distance (``inf`` on a miss)
    and ``prim[i]`` the triangle (-1 on a miss): of Embree's quad primID, the half the hit lies
    in (u + v > 1: the second, :func:`_pair_quads`), ``tri_of[quad_base[instID] + primID, half]``,
    plus ``offsets[instID]`` (instID 0 outside instances, :class:`InstancedEmbreeIntersector`).
    Occlusion (True): ``t[i]`` becomes ``-inf`` where something lies on the ray (Embree's
    convention) and ``prim`` is not touched. ``org``, ``dirs`` (m, 3) float32; ``t`` (m,)
    float32; ``prim`` (m,) int32; ``offsets``, ``quad_base`` (k,) int64; ``tri_of`` (q, 2) int32.
    """
    m = org.shape[0]
    n_blocks = (m + BLOCK_RAYS - 1) // BLOCK_RAYS
    for c in prange(n_blocks):
        f = slot_f[c]
        u = slot_u[c]
        addr = f.ctypes.data
        for i in range(c * BLOCK_RAYS, min(m, (c + 1) * BLOCK_RAYS)):
            _set_ray(f, u, org, dirs, i, t[i])
            if occlusion:
                _rtc_occluded1(scene, addr, 0)
                t[i] = f[_TFAR]
                continue
            u[_PRIM], u[_GEOM], u[_INST] = _INVALID_ID, _INVALID_ID, _INVALID_ID
            _rtc_intersect1(scene, addr, 0)
            if u[_GEOM] == _INVALID_ID:
                t[i] = np.inf
                prim[i] = -1
            else:
                t[i] = f[_TFAR]
                j = 0 if u[_INST] == _INVALID_ID else u[_INST]
                half = 1 if f[_U] + f[_V] > 1.0 else 0
                prim[i] = np.int32(offsets[j] + tri_of[quad_base[j] + u[_PRIM], half])


@njit(cache=True, nogil=True)
def _spread_bits(x):
    """The low 10 bits of ``x`` spread to every third bit (a Morton code's one axis)."""
    x &= 0x3FF
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


@njit(cache=True, nogil=True)
def coherent_order(org, bits):
    """Ray indices sorted by the Morton (Z-order) code of their origins on a grid of
    ``2**bits`` cells per axis over the origins' bounding box (counting sort, O(m + 8**bits)).

    Embree traverses the BVH far faster when consecutive rays start close together (shared
    nodes and triangles stay in cache); the tracer's secondary rays come in no such order.
    """
    m = org.shape[0]
    lo = np.empty(3, np.float32)
    scale = np.empty(3, np.float32)
    cells = 1 << bits
    for a in range(3):
        lo_a, hi_a = org[0, a], org[0, a]
        for i in range(1, m):
            lo_a = min(lo_a, org[i, a])
            hi_a = max(hi_a, org[i, a])
        lo[a] = lo_a
        scale[a] = (cells - 1) / (hi_a - lo_a) if hi_a > lo_a else 0.0
    key = np.empty(m, np.int64)
    count = np.zeros((1 << (3 * bits)) + 1, np.int64)
    for i in range(m):
        k = np.int64(0)
        for a in range(3):
            x = (org[i, a] - lo[a]) * scale[a]  # NaN and out-of-range origins go to the edge cells
            q = np.int64(min(max(x, 0.0), cells - 1)) if x == x else 0
            k |= _spread_bits(q) << a
        key[i] = k
        count[k + 1] += 1
    for j in range(1, count.shape[0]):
        count[j] += count[j - 1]
    order = np.empty(m, np.int64)
    for i in range(m):
        order[count[key[i]]] = i
        count[key[i]] += 1
    return order


_NO_OFFSETS = np.zeros(1, np.int64)
"""The ``offsets`` and ``quad_base`` of a scene without instances."""


@njit(cache=True, nogil=True)
def _pair_quads(tri):
    """Embree quads of the (n, 3, 3) triangles: consecutive triangles ``i``, ``i + 1`` that
    share an edge (two vertices bit for bit) become one quad, any other triangle a quad whose
    last vertex repeats its third. Returns the (q, 4, 3) float32 quads and ``tri_of`` (q, 2)
    int32, the triangle of each quad's first and second half.

    Embree intersects quad (v0, v1, v2, v3) as the triangles (v0, v1, v3) and (v2, v3, v1)
    and reports u + v <= 1 on the first and u + v >= 1 on the second: here (v0, v1, v3) is
    triangle ``i`` (its vertices rotated so that v0 is the one it does not share) and v2 the
    vertex of ``i + 1`` it does not share.
    """
    n = tri.shape[0]
    quads = np.empty((n, 4, 3), np.float32)
    tri_of = np.empty((n, 2), np.int32)
    q = 0
    i = 0
    while i < n:
        own, other = -1, -1
        if i + 1 < n:
            this_mask, next_mask = 0, 0  # bit a: vertex a is also in the other triangle
            for a in range(3):
                for b in range(3):
                    if (tri[i, a, 0] == tri[i + 1, b, 0] and tri[i, a, 1] == tri[i + 1, b, 1]
                            and tri[i, a, 2] == tri[i + 1, b, 2]):
                        this_mask |= 1 << a
                        next_mask |= 1 << b
            for a in range(3):
                if this_mask == 7 - (1 << a):
                    own = a
                if next_mask == 7 - (1 << a):
                    other = a
        if own >= 0 and other >= 0:
            for c in range(3):
                quads[q, 0, c] = tri[i, own, c]
                quads[q, 1, c] = tri[i, (own + 1) % 3, c]
                quads[q, 2, c] = tri[i + 1, other, c]
                quads[q, 3, c] = tri[i, (own + 2) % 3, c]
            tri_of[q, 0], tri_of[q, 1] = i, i + 1
            i += 2
        else:
            for c in range(3):
                quads[q, 0, c] = tri[i, 0, c]
                quads[q, 1, c] = tri[i, 1, c]
                quads[q, 2, c] = tri[i, 2, c]
                quads[q, 3, c] = tri[i, 2, c]
            tri_of[q, 0], tri_of[q, 1] = i, i
            i += 1
        q += 1
    return quads[:q], tri_of[:q].copy()  # the quads only until Embree has copied them


def _slots(m: int) -> tuple[np.ndarray, np.ndarray]:
    """64-byte aligned RTCRayHit slots for the blocks of ``m`` rays (float32 and uint32 views)."""
    n = max(1, -(-m // BLOCK_RAYS))
    raw = np.empty(n * SLOT_FLOATS + 16, np.float32)
    skip = (-raw.ctypes.data % 64) // 4
    f = raw[skip:skip + n * SLOT_FLOATS].reshape(n, SLOT_FLOATS)
    return f, f.view(np.uint32)


def _new_scene(quality: str):
    """(library, new Embree scene of build quality ``quality``); errors when Embree is
    unavailable or the quality unknown."""
    lib = _load()
    if lib is None:
        raise RuntimeError(f"direct Embree calls unavailable: {_ERROR}")
    if quality not in QUALITIES:
        raise ValueError(f"quality: expected one of {', '.join(QUALITIES)}, got {quality!r}")
    scene = lib.rtcNewScene(_DEVICE)
    lib.rtcSetSceneBuildQuality(scene, QUALITIES[quality])
    return lib, scene


def _commit(lib, scene, what: str):
    """Build the BVH of ``scene`` (Embree's own threads); an Embree error releases it and raises."""
    lib.rtcCommitScene(scene)
    err = lib.rtcGetDeviceError(_DEVICE)
    if err:
        lib.rtcReleaseScene(scene)
        raise RuntimeError(f"Embree error {err} while building a scene of {what}")
    return scene


class DirectEmbreeIntersector(RayQueries):
    """Nearest-hit and occlusion queries on an Embree 4 BVH of ``triangles`` (:class:`RayQueries`),
    called from Numba kernels; ``quality`` ({"low", "medium", "high"}) is the BVH build quality.
    Embree holds the triangles as quads (:func:`_pair_quads`); hits report triangle indices."""

    backend = "embree"

    def __init__(self, triangles: np.ndarray, quality: str = DEFAULT_QUALITY) -> None:
        tri = check_triangles(triangles)
        n = len(tri)
        quads, self._tri_of = _pair_quads(np.ascontiguousarray(tri, np.float32))
        m = len(quads)
        lib, scene = _new_scene(quality)
        self._lib = lib
        geom = lib.rtcNewGeometry(_DEVICE, _RTC_GEOMETRY_TYPE_QUAD)
        lib.rtcSetGeometryBuildQuality(geom, QUALITIES[quality])
        vptr = lib.rtcSetNewGeometryBuffer(geom, _RTC_BUFFER_TYPE_VERTEX, 0, _RTC_FORMAT_FLOAT3, 12, 4 * m)
        iptr = lib.rtcSetNewGeometryBuffer(geom, _RTC_BUFFER_TYPE_INDEX, 0, _RTC_FORMAT_UINT4, 16, m)
        if not vptr or not iptr:
            lib.rtcReleaseGeometry(geom)
            lib.rtcReleaseScene(scene)
            raise MemoryError(f"Embree could not allocate buffers for {n} triangles")
        ctypes.memmove(vptr, quads.ctypes.data, quads.nbytes)
        idx = np.arange(4 * m, dtype=np.uint32)
        ctypes.memmove(iptr, idx.ctypes.data, idx.nbytes)
        lib.rtcCommitGeometry(geom)
        lib.rtcAttachGeometry(scene, geom)
        lib.rtcReleaseGeometry(geom)
        self._scene = _commit(lib, scene, f"{n} triangles")
        self._offsets = self._quad_base = _NO_OFFSETS
        self.n_triangles = n
        self.quality = quality

    def __del__(self) -> None:
        scene, self._scene = getattr(self, "_scene", None), None
        if scene:
            self._lib.rtcReleaseScene(scene)

    def _hit_map(self):
        """``offsets``, ``quad_base``, ``tri_of`` of :func:`_query_kernel`."""
        return self._offsets, self._quad_base, self._tri_of

    def _intersect(self, o, d, tfar, prim, threads, coherent):
        with NumbaThreads(1 if len(o) < MIN_PARALLEL_RAYS else threads):
            if coherent:  # a beam's primary rays: the Z-order would not speed Embree up
                tfar[:] = np.inf
                _query_kernel(self._scene, o, d, tfar, prim, False, *_slots(len(o)), *self._hit_map())
                return
            order = coherent_order(o, CELL_BITS)
            ts, ps = np.full_like(tfar, np.inf), np.empty_like(prim)
            _query_kernel(self._scene, *take_rays(o, d, order), ts, ps, False, *_slots(len(o)), *self._hit_map())
        tfar[order], prim[order] = ts, ps

    def _occluded(self, o, d, tmax, out, threads):
        order = coherent_order(o, CELL_BITS)
        t = tmax[order]
        with NumbaThreads(1 if len(o) < MIN_PARALLEL_RAYS else threads):
            _query_kernel(self._scene, *take_rays(o, d, order), t, _NO_PRIM, True, *_slots(len(o)),
                          *self._hit_map())
        out[order] = t == -np.inf  # Embree sets tfar = -inf on an occluded ray


class InstancedEmbreeIntersector(DirectEmbreeIntersector):
    """Queries on a two-level Embree BVH: rigid instances of prebuilt prototype BVHs.

    Only the top level (one box per instance) is built here, so a new arrangement of
    prototypes costs far less than a BVH over all its triangles (docs/validation.md, "Speed").
    A hit in instance ``j`` reports triangle ``offsets[j] + primID`` (``primID`` within its
    prototype), so that per-triangle arrays of the arrangement line up with instance order.

    Parameters
    ----------
    prototypes : sequence of DirectEmbreeIntersector
        Built prototypes (kept alive while this BVH lives).
    which : (k,) int
        Prototype of each instance.
    transforms : (k, 3, 4) float
        Prototype frame -> this BVH's frame: [R | t], x' = R x + t.
    offsets : (k,) int
        Index of each instance's first triangle in the arrangement.
    quality : {"low", "medium", "high"}
        Build quality of the top level.
    """

    def __init__(self, prototypes, which, transforms, offsets, quality: str = "medium") -> None:
        which = np.asarray(which, np.int64)
        xfm = np.asarray(transforms, np.float64)
        if which.ndim != 1 or xfm.shape != (len(which), 3, 4) or len(offsets) != len(which) or not len(which):
            raise ValueError(f"instances: expected (k,) prototypes, (k, 3, 4) transforms and (k,) offsets, "
                             f"got {which.shape}, {xfm.shape}, {len(offsets)}")
        if which.min() < 0 or which.max() >= len(prototypes):
            raise ValueError(f"which: prototype index outside [0, {len(prototypes)})")
        if not np.all(np.isfinite(xfm)):
            raise ValueError("transforms: non-finite values")
        self._prototypes = list(prototypes)
        lib, scene = _new_scene(quality)
        self._lib = lib
        columns = np.ascontiguousarray(xfm.transpose(0, 2, 1), np.float32)  # (k, 4, 3): column-major
        for j, p in enumerate(which):
            geom = lib.rtcNewGeometry(_DEVICE, _RTC_GEOMETRY_TYPE_INSTANCE)
            lib.rtcSetGeometryInstancedScene(geom, self._prototypes[p]._scene)
            lib.rtcSetGeometryTransform(geom, 0, _RTC_FORMAT_FLOAT3X4_COLUMN_MAJOR, columns[j].ctypes.data)
            lib.rtcCommitGeometry(geom)
            lib.rtcAttachGeometry(scene, geom)  # geometry IDs 0, 1, ... = instance order
            lib.rtcReleaseGeometry(geom)
        self._scene = _commit(lib, scene, f"{len(which)} instances")
        self._offsets = np.ascontiguousarray(offsets, np.int64)
        starts = np.cumsum([0] + [len(p._tri_of) for p in self._prototypes])
        self._quad_base = np.ascontiguousarray(starts[which], np.int64)
        self._tri_of = np.concatenate([p._tri_of for p in self._prototypes])
        self.n_triangles = int(sum(self._prototypes[p].n_triangles for p in which))
        self.quality = quality
