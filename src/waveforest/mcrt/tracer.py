"""The wavefront Monte Carlo ray tracer: scene + pulses -> sigma(t) per pulse (docs/method.md §(d)).

All rays of a chunk of pulses advance one scattering order per step: one batched Embree
intersection call, one Numba kernel (receiver contributions, binning, new rays), one batched
occlusion call for the visibility rays of orders >= 2, and a serial binning pass.

Coordinates: sensors may be kilometres from the scene. Each pulse's rays start on the plane
perpendicular to its axis just before the scene's bounding box (in the scene's internal
float32 frame, a few metres around the origin); the skipped path is carried in float64 and
every time is computed in float64.

Time: ``sigma[i, k]`` holds the contributions whose two-way time from emission (total path
sensor -> hit 1 -> ... -> hit n -> receiver, divided by the speed of light) lies in
``[t0_ns[i] + k bin_ns, t0_ns[i] + (k + 1) bin_ns)``. ``t0_ns`` lies :data:`T0_LEAD_NS`
before the earliest possible return (the scene's bounding box along the beam); the window
is ``window_ns`` long, and contributions after it are not binned but summed in
``sigma_dropped`` (they are still in ``order_totals``).

Randomness: a counter-based generator keyed by (seed, pulse index in the call, ray, order,
draw) (:mod:`waveforest.mcrt.kernels`), so the same seed gives the identical result whatever the threads,
the chunking and the parallel mode. ``sampler="sobol"`` draws the same uniforms from a per-pulse
Owen-scrambled Sobol' sequence instead (randomized QMC); ``roulette`` ends low-power paths by
an unbiased Russian roulette (a weight window). The caller chooses ``n_rays``, ``sampler`` and
``roulette`` (config ``mcrt``); the defaults of ``max_order``, ``bin_ns``, ``viewed_diameter_m`` and
``window_ns`` are the config schema's (``tests/test_mcrt_defaults.py`` compares them).

Embree: the default intersector calls ``rtcIntersect1`` / ``rtcOccluded1`` from a Numba
kernel (:mod:`waveforest.mcrt.backends.embree`) on a BVH of HIGH build quality.

Threads (``parallel``): ``pulses`` (default) runs chunks of pulses concurrently, one serial
wavefront per thread (Embree calls and kernels are ``nogil``); ``rays`` splits every Embree
call and Numba kernel of one wavefront over the threads (``prange``). Both give identical
results.

Scene reuse: a scene :func:`prepare` d once can be traced for any number of pulses; whether
pulses may share an instance (a pool of instances with random placement) is the calling
stage's decision. Where the CPU time goes, the thread modes and the cost of a BVH build
against tracing: docs/validation.md, "Speed" (``benchmarks/mcrt.py``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from waveforest.constants import BIN_NS, C_M_PER_NS, RANGE_PER_NS, RAY_EPS_M
from waveforest.effects import CATALOGUE, SPECULAR_PHONG_EXPONENT
from waveforest.mcrt.beams import Beams
from waveforest.mcrt.kernels import (
    MISS_KIND,
    SAMPLERS,
    BeamFrame,
    Scattered,
    accumulate,
    beam_keys,
    compact,
    emit_rays,
    scatter,
    take_rays,
)
from waveforest.mcrt.prepare import PreparedScene, prepare
from waveforest.mcrt.threads import MIN_PARALLEL_RAYS, NumbaThreads, default_threads
from waveforest.rng import named_seed
from waveforest.scene import Scene
from waveforest.workers import unordered_map

DEFAULT_WINDOW_NS = 100.0
"""Default sigma window, ns of two-way time after t0 (15 m of one-way range: a 6 x 6 m scene
with 10 orders of scattering rarely returns light later; later light is counted as dropped)."""

T0_LEAD_NS = 1.0
"""Bin 0 starts this long before the earliest possible return, ns."""

START_MARGIN_M = 0.05
"""Rays start this far before the scene's bounding box along the beam, m."""

CHUNK_RAYS = 240_000
"""Rays per wavefront (pulses are traced in chunks of ``CHUNK_RAYS // n_rays``)."""

HIGH_QUALITY_MIN_RAYS = 12 * 30_000
"""``trace`` of an unprepared scene builds a HIGH-quality BVH from this many emitted rays on
(12 pulses of 30,000 rays), else a MEDIUM one: HIGH costs more to build and saves CPU time
in proportion to the rays traced (the break-even measured on the vegetation scenes:
docs/validation.md, "Speed")."""


def bvh_quality(n_pulses: int, n_rays: int) -> str:
    """The BVH build quality that pays for ``n_pulses`` pulses of ``n_rays`` rays each:
    "high" from :data:`HIGH_QUALITY_MIN_RAYS` rays on, else "medium"."""
    return "high" if int(n_pulses) * int(n_rays) >= HIGH_QUALITY_MIN_RAYS else "medium"


CHUNKS_PER_WORKER = 4
"""In ``parallel="pulses"``, pulses are split into about this many chunks per thread."""

PARALLEL_MODES = ("pulses", "rays")
"""How ``trace`` uses its threads: whole chunks of pulses per thread, or every call split."""


@dataclass(frozen=True)
class TraceResult:
    """sigma(t) of a batch of pulses.

    Attributes
    ----------
    sigma : (n, n_bins) float64, sr^-1 per unit emitted power
        Per-bin sum of receiver contributions (a Lambertian plane at normal incidence gives
        a total of rho / pi).
    t0_ns : (n,) float64, ns
        Two-way time from emission of the left edge of bin 0.
    bin_ns : float
        Bin width, ns of two-way time.
    order_totals : (n, max_order) float64
        Total contribution of each scattering order (binned and dropped).
    first_hit_counts : (n, 5) int64
        Rays whose first hit is a ground, leaf, wood or other element, and rays that missed.
    sigma_dropped : (n,) float64
        Contributions later than the window (not in ``sigma``).
    n_rays : int
        Rays per pulse.
    sigma_by_order : (n, max_order, n_bins) float64 or None
        sigma split by scattering order (``trace(..., by_order=True)``).
    """

    sigma: np.ndarray
    t0_ns: np.ndarray
    bin_ns: float
    order_totals: np.ndarray
    first_hit_counts: np.ndarray
    sigma_dropped: np.ndarray
    n_rays: int
    sigma_by_order: np.ndarray | None = None

    def __len__(self) -> int:
        return self.sigma.shape[0]

    @property
    def n_bins(self) -> int:
        return self.sigma.shape[1]

    @property
    def max_order(self) -> int:
        return self.order_totals.shape[1]

    @property
    def total(self) -> np.ndarray:
        """(n,) total sigma of each pulse, all orders, binned or dropped."""
        return self.order_totals.sum(axis=1)

    def times_ns(self) -> np.ndarray:
        """(n, n_bins) two-way time from emission of each bin's left edge, ns."""
        return self.t0_ns[:, None] + self.bin_ns * np.arange(self.n_bins)[None, :]

    def frame(self, i: int = 0):
        """sigma(t) of pulse ``i`` as a table.

        Columns: ``time_ns`` (two-way time from emission, bin left edge), ``range_m``
        (one-way range of that time), ``sigma`` and, if traced ``by_order``,
        ``sigma_order_1`` ... ``sigma_order_<max_order>``.
        """

        t = self.t0_ns[i] + self.bin_ns * np.arange(self.n_bins)
        cols = {"time_ns": t, "range_m": t * RANGE_PER_NS, "sigma": self.sigma[i]}
        if self.sigma_by_order is not None:
            for k in range(self.max_order):
                cols[f"sigma_order_{k + 1}"] = self.sigma_by_order[i, k]
        return pd.DataFrame(cols)


def master_key(seed) -> np.uint64:
    """The uint64 key of the counter-based generator from an int seed or a numpy Generator."""
    if isinstance(seed, np.random.Generator):
        return np.uint64(seed.integers(0, 2**64, dtype=np.uint64))
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed: expected a non-negative int or a numpy Generator, got {seed!r}")
    return np.uint64(named_seed("mcrt_key", int(seed), bits=64))


def start_plane(bounds: np.ndarray, sensor: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Distance from each sensor, along its axis, of a plane just before the scene's box.

    Parameters
    ----------
    bounds : (2, 3) float64, m
        Bounding box [min, max] (same frame as ``sensor``).
    sensor : (nb, 3) float64, m
    axis : (nb, 3) float64, unit

    Returns
    -------
    (nb,) float64, m
        min over the 8 box corners of (corner - sensor) . axis, minus
        :data:`START_MARGIN_M`, and never negative.
    """
    corners = np.array([[bounds[i, 0], bounds[j, 1], bounds[k, 2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    depth = np.einsum("bck,bk->bc", corners[None, :, :] - sensor[:, None, :], axis)
    return np.maximum(depth.min(axis=1) - START_MARGIN_M, 0.0)


def survival_by_order(survival, max_order: int) -> np.ndarray:
    """(max_order + 1,) float64: the continuation probability after scattering at each order
    (index = order; index 0 unused), from a scalar or a per-order sequence whose last value
    repeats; every value in (0, 1]."""
    q = np.atleast_1d(np.asarray(survival, dtype=np.float64))
    if q.ndim != 1 or q.size == 0 or not np.all((q > 0) & (q <= 1)):
        raise ValueError(f"survival: expected probabilities in (0, 1], got {survival!r}")
    out = np.ones(max_order + 1)
    k = min(q.size, max_order)
    out[1:1 + k] = q[:k]
    out[1 + k:] = q[-1]
    return out


def _check(n_rays, max_order, bin_ns, viewed_diameter_m, window_ns, specular, hotspot, sampler, roulette):
    if not isinstance(n_rays, (int, np.integer)) or n_rays < 1:
        raise ValueError(f"n_rays: expected a positive int, got {n_rays!r}")
    if not isinstance(max_order, (int, np.integer)) or max_order < 1:
        raise ValueError(f"max_order: expected a positive int, got {max_order!r}")
    for name, v in (("bin_ns", bin_ns), ("viewed_diameter_m", viewed_diameter_m), ("window_ns", window_ns)):
        if not (np.isfinite(v) and v > 0):
            raise ValueError(f"{name}: expected a positive number, got {v!r}")
    lo, hi = 0.0, 1.0
    if not lo <= specular <= hi:
        raise ValueError(f"specular: expected a fraction in [0, 1], got {specular!r}")
    if not (np.isfinite(hotspot) and hotspot >= 0):
        raise ValueError(f"hotspot: expected a factor >= 0 (off = {CATALOGUE['hotspot'].off}), got {hotspot!r}")
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler: expected one of {', '.join(SAMPLERS)}, got {sampler!r}")
    if not (np.isfinite(roulette) and 0 <= roulette <= 1):
        raise ValueError(f"roulette: expected a power fraction in [0, 1], got {roulette!r}")


@dataclass(frozen=True)
class _ChunkSettings:
    """What every chunk of one :func:`trace` call shares (its checked arguments)."""

    key: np.uint64
    """Master key of the counter-based generator (:func:`master_key`)."""
    n_rays: int
    max_order: int
    bin_ns: float
    n_bins: int
    viewed_diameter_m: float
    specular: float
    hotspot: float
    by_order: bool
    sampler: str
    survive: np.ndarray
    """(max_order + 1,) continuation probability after each order (:func:`survival_by_order`)."""
    roulette: float

    @property
    def layers(self) -> int:
        """sigma layers kept per pulse: one per order (``by_order``), else one."""
        return self.max_order if self.by_order else 1


def _trace_chunk(prepared: PreparedScene, beams: Beams, index: np.ndarray, st: _ChunkSettings,
                threads: int | None):
    """Trace one chunk of beams (``index`` = their positions in the trace call), one wavefront
    per scattering order.

    Returns (sigma (nb, layers, n_bins), dropped (nb,), order_totals (nb, max_order),
    first_hit_counts (nb, 5), t0_ns (nb,)).
    """
    nb = len(beams)
    sensor = beams.origin - prepared.shift
    axis = beams.direction
    plane = start_plane(prepared.bounds, sensor, axis)
    t0 = 2.0 * plane / C_M_PER_NS - T0_LEAD_NS
    frame = BeamFrame(np.ascontiguousarray(sensor), np.ascontiguousarray(axis), t0, beam_keys(st.key, index))
    acc = np.zeros((nb, st.layers, st.n_bins))
    dropped = np.zeros(nb)
    totals = np.zeros((nb, st.max_order))

    rays = emit_rays(frame, beams.footprint_m, beams.range_m, plane, st.n_rays, st.sampler)
    buffers = rays  # the live rays are packed into the emission arrays after each order
    work = Scattered.empty(len(rays))
    isect = prepared.intersector
    first = None
    for order in range(1, st.max_order + 1):
        if len(rays) == 0:
            break
        tfar, prim = isect.intersect(rays.origin, rays.direction, threads=threads)
        if order == 1:
            first = _first_hits(prepared, rays, prim, nb)
        out = scatter(order, order == st.max_order, rays, tfar, prim, prepared, frame, st.n_bins, st.bin_ns,
                      st.viewed_diameter_m, st.specular, SPECULAR_PHONG_EXPONENT, st.hotspot, RAY_EPS_M,
                      out=work, sampler=st.sampler, survive=st.survive, floor_power=st.roulette / st.n_rays)
        counted = np.flatnonzero(out.value > 0.0)
        if order > 1 and counted.size:
            counted = _visible(isect, out, counted, threads)
        accumulate(counted, rays.beam, out.value, out.bin, order, acc, dropped, totals, st.by_order)
        if order < st.max_order:
            rays = compact(out, rays, buffers)
    return acc, dropped, totals, first, t0


def _first_hits(prepared: PreparedScene, rays, prim: np.ndarray, nb: int) -> np.ndarray:
    """(nb, 5) int64: rays of each beam whose first hit is of each kind, and misses (last column)."""
    code = np.where(prim >= 0, prepared.kind_of(np.maximum(prim, 0)), MISS_KIND)
    return np.bincount(rays.beam * (MISS_KIND + 1) + code,
                       minlength=nb * (MISS_KIND + 1)).reshape(nb, MISS_KIND + 1)


def _visible(isect, out: Scattered, counted: np.ndarray, threads: int | None) -> np.ndarray:
    """The contributions of ``counted`` whose visibility ray to the receiver is not occluded."""
    with NumbaThreads(1 if counted.size < MIN_PARALLEL_RAYS else threads):
        so, sd = take_rays(out.shadow_origin, out.shadow_direction, counted)
    blocked = isect.occluded(so, sd, out.shadow_tmax[counted], threads=threads)
    return counted[~blocked]


def _chunk_plan(n: int, n_rays: int, chunk_rays: int, threads: int,
                parallel: str) -> tuple[list[tuple[int, int]], bool]:
    """Pulse ranges ``[a, b)`` traced as one wavefront each, and whether they run
    concurrently (``parallel="pulses"`` with several threads and pulses).

    A chunk holds ``chunk_rays // n_rays`` pulses (at least one); traced concurrently, at most
    ``ceil(n / (threads * CHUNKS_PER_WORKER))`` so that workers that finish early take more.
    An unknown ``parallel`` raises ValueError.
    """
    if parallel not in PARALLEL_MODES:
        raise ValueError(f"parallel: expected one of {', '.join(PARALLEL_MODES)}, got {parallel!r}")
    per_chunk = max(1, chunk_rays // n_rays)
    by_pulses = parallel == "pulses" and threads > 1 and n > 1
    if by_pulses:  # several chunks per worker, handed out as workers free up (load balance)
        per_chunk = min(per_chunk, max(1, -(-n // (threads * CHUNKS_PER_WORKER))))
    return [(a, min(n, a + per_chunk)) for a in range(0, n, per_chunk)], by_pulses


def trace(scene: Scene | PreparedScene, beams: Beams, n_rays: int, max_order: int = 10,
          bin_ns: float = BIN_NS, viewed_diameter_m: float = 5.0, seed=0, *, sampler: str, roulette: float,
          specular: float = 0.0, hotspot: float = 1.0, window_ns: float = DEFAULT_WINDOW_NS,
          by_order: bool = False, chunk_rays: int = CHUNK_RAYS, threads: int | None = None,
          parallel: str = "pulses", progress: bool = False, survival=1.0) -> TraceResult:
    """Forward Monte Carlo ray tracing of LiDAR pulses through a scene (docs/method.md §(d), Eq. 2).

    Parameters
    ----------
    scene : Scene or PreparedScene
        Triangles with rho, tau, kind; prepare it once (:func:`prepare`) to trace it often
        (a Scene is prepared here, its BVH quality chosen by :func:`bvh_quality`).
    beams : Beams
        The pulses: sensor positions, unit directions, 1/e footprints.
    n_rays : int
        Rays per pulse, each with power 1 / n_rays.
    max_order : int
        Highest scattering order traced.
    bin_ns : float
        sigma bin width, ns of two-way time.
    viewed_diameter_m : float
        Diameter of the receiver's viewed cylinder around the beam axis, m: only scattering
        points within ``viewed_diameter_m / 2`` of the axis (perpendicular distance;
        the horizontal circle at nadir) contribute.
    seed : int or numpy.random.Generator
        Same seed, same beams -> identical result (whatever the threads or chunking).
    sampler : {"random", "sobol"}
        Uniforms of the beam positions, branches and directions: pseudo-random, or a
        per-pulse Owen-scrambled Sobol' sequence (randomized quasi-Monte Carlo, unbiased;
        :mod:`.kernels`); ``sobol`` works best with ``n_rays`` a power of two.
    roulette : float
        Weight-window Russian roulette: a ray whose power would fall below ``roulette`` times
        its emitted power (1 / n_rays) continues with probability power / that floor, and then
        carries the floor (e.g. after a ground hit, rho 0.3 < 0.5). 0 = off.
    specular : float
        Effect ``specular``: fraction of the leaf (kind 1) reflectance that is a Phong lobe
        of exponent :data:`waveforest.effects.SPECULAR_PHONG_EXPONENT`; 0 = off.
    hotspot : float
        Effect ``hotspot``: factor on order-1 contributions of vegetation (kind != 0); 1 = off.
    window_ns : float
        Length of the sigma window after ``t0_ns``, ns.
    by_order : bool
        Also return sigma split by order (``sigma_by_order``).
    chunk_rays : int
        Rays per wavefront (bounds memory: about 150 bytes per ray).
    threads : int, optional
        Threads to use (default: Numba's thread count, set by ``--threads``).
    parallel : {"pulses", "rays"}
        How the threads share the work: ``pulses`` traces chunks of pulses concurrently,
        one serial wavefront per thread (a single pulse falls back to ``rays``); ``rays`` splits every Embree call and
        Numba kernel of one wavefront over the threads. Results are identical.
    progress : bool
        Show a progress bar over chunks (stderr).
    survival : float or sequence of float
        Russian roulette: probability in (0, 1] that a ray scattered at order n continues to
        order n + 1 (power divided by it); a sequence gives orders 1, 2, ... and its last
        value holds for the higher orders. 1 = every ray continues (docs/method.md §(d)).

    Returns
    -------
    TraceResult
    """
    if not isinstance(beams, Beams):
        raise TypeError(f"beams: expected waveforest.mcrt.Beams, got {type(beams).__name__}")
    _check(n_rays, max_order, bin_ns, viewed_diameter_m, window_ns, specular, hotspot, sampler, roulette)
    st = _ChunkSettings(
        key=master_key(seed), n_rays=int(n_rays), max_order=int(max_order), bin_ns=float(bin_ns),
        n_bins=int(math.ceil(window_ns / bin_ns - 1e-9)), viewed_diameter_m=float(viewed_diameter_m),
        specular=float(specular), hotspot=float(hotspot), by_order=by_order, sampler=sampler,
        survive=survival_by_order(survival, max_order), roulette=float(roulette))
    if isinstance(scene, PreparedScene):
        prepared = scene
    else:  # a HIGH-quality BVH pays for its longer build only over enough rays
        prepared = prepare(scene, quality=bvh_quality(len(beams), n_rays))
    threads = default_threads() if threads is None else max(1, int(threads))
    chunks, by_pulses = _chunk_plan(len(beams), st.n_rays, int(chunk_rays), threads, parallel)
    return _trace_chunks(prepared, beams, st, chunks, by_pulses, threads, progress)


def _trace_chunks(prepared: PreparedScene, beams: Beams, st: _ChunkSettings, chunks: list[tuple[int, int]],
                  by_pulses: bool, threads: int, progress: bool) -> TraceResult:
    """Trace every chunk ``[a, b)`` of ``beams`` (concurrently if ``by_pulses``) and assemble the result."""
    n = len(beams)
    sigma = np.zeros((n, st.layers, st.n_bins))
    dropped = np.zeros(n)
    totals = np.zeros((n, st.max_order))
    first = np.zeros((n, MISS_KIND + 1), np.int64)
    t0 = np.zeros(n)

    def run_chunk(ab, embree_threads):
        a, b = ab
        return _trace_chunk(prepared, beams[a:b], np.arange(a, b), st, embree_threads)

    if by_pulses:  # one serial wavefront per worker thread, chunks as workers free up
        results = unordered_map(lambda ab: run_chunk(ab, 1), chunks, threads)
    else:
        results = ((i, run_chunk(ab, threads)) for i, ab in enumerate(chunks))
    if progress:
        from tqdm import tqdm

        results = tqdm(results, total=len(chunks), desc="trace", unit="chunk", leave=False)
    with NumbaThreads(None if by_pulses else threads):  # the kernels' prange threads
        for i, (acc, drop, tot, fh, t0c) in results:
            a, b = chunks[i]
            sigma[a:b], dropped[a:b], totals[a:b], first[a:b], t0[a:b] = acc, drop, tot, fh, t0c
    return TraceResult(
        sigma=sigma.sum(axis=1),
        t0_ns=t0,
        bin_ns=st.bin_ns,
        order_totals=totals,
        first_hit_counts=first,
        sigma_dropped=dropped,
        n_rays=st.n_rays,
        sigma_by_order=sigma if st.by_order else None,
    )
