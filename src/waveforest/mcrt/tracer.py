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
the chunking and the parallel mode. Ray budget: ``n_rays`` per pulse, or (``tolerance``) an adaptive
budget per pulse that stops once the recorded waveform's Monte Carlo error falls to a fraction
of the digitiser noise (:func:`_trace_chunk_adaptive`; docs/method.md §(d), "Ray budget"). ``sampler="sobol"`` draws the same uniforms from a per-pulse
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
    first_hits,
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

BATCHES = 32
"""Batches of consecutive rays whose spread gives a pulse's Monte Carlo error under the adaptive
budget (the estimate's own relative SD is about 1 / sqrt(2 (BATCHES - 1)))."""

GROWTH = 4
"""Largest factor by which a round of the adaptive budget multiplies a pulse's rays."""

STEPS_PER_OCTAVE = 4
"""The adaptive budget's ray counts are multiples of 2^(floor(log2 N) - 2): four per octave."""

ERROR_STEP_NS = 1.0
"""Sampling step of the recorded waveform in the adaptive budget's error estimate, ns."""

SUPPORT_SD = 0.1
"""The recorded waveform's error is averaged over the samples whose mean signal reaches this many
noise SDs (:func:`waveform_error`)."""

ADAPTIVE_CHUNK_PULSES = 32
"""At most this many pulses per chunk under the adaptive budget (bounds the replicates' memory)."""


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
        Rays per pulse (fixed budget); under the adaptive budget the most any pulse used.
    sigma_by_order : (n, max_order, n_bins) float64 or None
        sigma split by scattering order (``trace(..., by_order=True)``).
    rays : (n,) int64 or None
        Rays each pulse used (the adaptive budget varies them; fixed: all ``n_rays``).
    mc_error : (n,) float64 or None
        Under the adaptive budget, each pulse's estimated Monte Carlo error of its recorded
        waveform when it stopped, in noise SDs (:func:`waveform_error`; above the tolerance
        only where the pulse reached ``max_rays``); NaN under a fixed budget.
    """

    sigma: np.ndarray
    t0_ns: np.ndarray
    bin_ns: float
    order_totals: np.ndarray
    first_hit_counts: np.ndarray
    sigma_dropped: np.ndarray
    n_rays: int
    sigma_by_order: np.ndarray | None = None
    rays: np.ndarray | None = None
    mc_error: np.ndarray | None = None

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
class _Adaptive:
    """The checked adaptive budget of one :func:`trace` call."""

    tolerance: float
    min_rays: int
    max_rays: int
    kernel: np.ndarray
    """(n_k,) the system pulse on the sigma grid."""
    noise: np.ndarray
    """(n,) noise SD of each pulse of the call, in the units of kernel (x) sigma."""


def _pow2_floor(x: int) -> int:
    return 1 << (max(1, int(x)).bit_length() - 1)


def _adaptive(tolerance, min_rays, max_rays, kernel, noise, n: int) -> _Adaptive | None:
    """The checked adaptive budget of a trace of ``n`` pulses (None when ``tolerance`` is None)."""
    if tolerance is None:
        return None
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance: expected a positive fraction of the noise SD or None, got {tolerance!r}")
    for name, v in (("min_rays", min_rays), ("max_rays", max_rays)):
        if not isinstance(v, (int, np.integer)) or v < 2 * BATCHES:
            raise ValueError(f"{name}: expected an int >= {2 * BATCHES}, got {v!r}")
    if max_rays < min_rays:
        raise ValueError(f"max_rays: expected >= min_rays ({min_rays}), got {max_rays!r}")
    if kernel is None or noise is None:
        raise ValueError("tolerance: the adaptive budget needs the system pulse (kernel) and the noise SD (noise)")
    k = np.ascontiguousarray(kernel, np.float64)
    if k.ndim != 1 or k.size == 0 or not np.all(np.isfinite(k)) or k.max() <= 0:
        raise ValueError("kernel: expected a finite 1-D system pulse with a positive peak")
    sd = np.broadcast_to(np.asarray(noise, np.float64), (n,)).copy()
    if not np.all(np.isfinite(sd) & (sd > 0)):
        raise ValueError("noise: expected a positive noise SD per pulse")
    lo = _pow2_floor(min_rays)
    hi = max(lo, _pow2_floor(max_rays))
    return _Adaptive(float(tolerance), lo, hi, k, sd)


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
    adaptive: _Adaptive | None = None
    """The adaptive budget (None: ``n_rays`` rays per pulse)."""

    @property
    def layers(self) -> int:
        """sigma layers kept per pulse: one per order (``by_order``), else one."""
        return self.max_order if self.by_order else 1


def _frame(prepared: PreparedScene, beams: Beams, keys: np.ndarray) -> tuple[BeamFrame, np.ndarray]:
    """The internal-frame constants of ``beams`` with stream keys ``keys``, and their start planes, m."""
    sensor = beams.origin - prepared.shift
    axis = beams.direction
    plane = start_plane(prepared.bounds, sensor, axis)
    t0 = 2.0 * plane / C_M_PER_NS - T0_LEAD_NS
    return BeamFrame(np.ascontiguousarray(sensor), np.ascontiguousarray(axis), t0, keys), plane


def _wave(prepared: PreparedScene, frame: BeamFrame, footprint_m, range_m, plane: np.ndarray,
          st: _ChunkSettings, n_rays: int, first_ray: int, threads: int | None):
    """Trace rays ``first_ray .. first_ray + n_rays - 1`` of every beam of ``frame``, each of power
    1 / n_rays, one wavefront per scattering order.

    Returns (sigma (nb, layers, n_bins), dropped (nb,), order_totals (nb, max_order),
    first_hit_counts (nb, 5)).
    """
    nb = len(frame)
    acc = np.zeros((nb, st.layers, st.n_bins))
    dropped = np.zeros(nb)
    totals = np.zeros((nb, st.max_order))
    rays = emit_rays(frame, footprint_m, range_m, plane, n_rays, st.sampler, first_ray=first_ray)
    buffers = rays  # the live rays are packed into the emission arrays after each order
    work = Scattered.empty(len(rays))
    isect = prepared.intersector
    first = None
    for order in range(1, st.max_order + 1):
        if len(rays) == 0:
            break
        tfar, prim = isect.intersect(rays.origin, rays.direction, threads=threads, coherent=order == 1)
        if order == 1:
            first = first_hits(rays.beam, prim, prepared.tri_data, nb)
        out = scatter(order, order == st.max_order, rays, tfar, prim, prepared, frame, st.n_bins, st.bin_ns,
                      st.viewed_diameter_m, st.specular, SPECULAR_PHONG_EXPONENT, st.hotspot, RAY_EPS_M,
                      out=work, sampler=st.sampler, survive=st.survive, floor_power=st.roulette / n_rays)
        counted = np.flatnonzero(out.value > 0.0)
        if order > 1 and counted.size:
            counted = _visible(isect, out, counted, threads)
        accumulate(counted, rays.beam, out.value, out.bin, order, acc, dropped, totals, st.by_order)
        if order < st.max_order:
            rays = compact(out, rays, buffers)
    if first is None:
        first = np.zeros((nb, MISS_KIND + 1), np.int64)
    return acc, dropped, totals, first


def _trace_chunk(prepared: PreparedScene, beams: Beams, index: np.ndarray, st: _ChunkSettings,
                 threads: int | None):
    """Trace one chunk of beams (``index`` = their positions in the trace call): ``st.n_rays``
    rays each, or the adaptive budget of ``st.adaptive`` (:func:`_trace_chunk_adaptive`).

    Returns (sigma (nb, layers, n_bins), dropped (nb,), order_totals (nb, max_order),
    first_hit_counts (nb, 5), t0_ns (nb,), rays (nb,), mc_error (nb,): NaN for a fixed budget).
    """
    if st.adaptive is not None:
        return _trace_chunk_adaptive(prepared, beams, index, st, threads)
    frame, plane = _frame(prepared, beams, beam_keys(st.key, index))
    acc, dropped, totals, first = _wave(prepared, frame, beams.footprint_m, beams.range_m, plane, st, st.n_rays,
                                        0, threads)
    nb = len(beams)
    return acc, dropped, totals, first, frame.t0_ns, np.full(nb, st.n_rays, np.int64), np.full(nb, np.nan)


def _trace_chunk_adaptive(prepared: PreparedScene, beams: Beams, index: np.ndarray, st: _ChunkSettings,
                          threads: int | None):
    """The adaptive ray budget of one chunk of beams (docs/method.md §(d), "Ray budget").

    A pulse that stops at N rays has exactly the sigma of a fixed budget of N rays (the first N
    points of its scrambled Sobol' sequence; the same stream key). N starts at ``min_rays`` (a
    power of two: a complete Sobol' net) and a round extends the pulses still running from N to
    the rays the error calls for (variance ~ 1 / N), rounded up to a quarter octave
    (:func:`next_budget`, at most :data:`GROWTH` x N). The error comes from :data:`BATCHES`
    batch sums: the first round's are consecutive nets of N / BATCHES rays, and each round
    appends a consecutive block of the new rays to each batch, so all batches hold the same
    rays; their spread ignores the joint stratification of the Sobol' points, so the error is
    overestimated, never under on average. A pulse stops once it is at most ``tolerance`` noise
    SDs (:func:`waveform_error`), or at ``max_rays``.
    """
    ad = st.adaptive
    nb, k = len(beams), BATCHES
    frame, plane = _frame(prepared, beams, beam_keys(st.key, index))
    total = np.zeros((nb, st.layers, st.n_bins))  # sums of contributions at unit power per ray
    dropped = np.zeros(nb)
    totals = np.zeros((nb, st.max_order))
    first = np.zeros((nb, MISS_KIND + 1), np.int64)
    batches = np.zeros((nb, k, st.n_bins))  # sum of each batch of N / k consecutive rays
    done = np.zeros(nb, np.int64)  # rays traced so far (N)
    error = np.full(nb, np.nan)  # the estimate when each pulse stopped
    target = np.full(nb, ad.min_rays, np.int64)
    noise = ad.noise[index]
    active = np.arange(nb)
    while active.size:
        for n0, n1 in sorted({(int(done[i]), int(target[i])) for i in active}):
            pulses = active[(done[active] == n0) & (target[active] == n1)]
            size = (n1 - n0) // k  # each batch gains one block of consecutive new rays
            per_wave = max(1, CHUNK_RAYS // (n1 - n0))
            for w in range(0, pulses.size, per_wave):
                p = pulses[w:w + per_wave]
                v = np.repeat(p, k)
                sub = BeamFrame(frame.sensor[v], frame.axis[v], frame.t0_ns[v], frame.key[v])
                start = n0 + size * np.tile(np.arange(k), p.size)
                acc, drop, tot, fh = _wave(prepared, sub, beams.footprint_m[v], beams.range_m[v], plane[v], st,
                                           size, start, threads)
                acc *= size
                per = acc.reshape(p.size, k, st.layers, st.n_bins)
                total[p] += per.sum(axis=1)
                dropped[p] += (drop * size).reshape(p.size, k).sum(axis=1)
                totals[p] += (tot * size).reshape(p.size, k, st.max_order).sum(axis=1)
                first[p] += fh.reshape(p.size, k, MISS_KIND + 1).sum(axis=1)
                batches[p] += per.sum(axis=2)
        done[active] = target[active]
        err = waveform_error(batches[active] / (done[active] // k)[:, None, None], ad.kernel, noise[active],
                             st.bin_ns)
        error[active] = err
        stop = (err <= ad.tolerance) | (done[active] >= ad.max_rays)
        go = active[~stop]
        target[go] = next_budget(done[go], err[~stop] / ad.tolerance, ad.max_rays)
        active = go
    scale = 1.0 / done
    return (total * scale[:, None, None], dropped * scale, totals * scale[:, None], first, frame.t0_ns, done, error)


def next_budget(done: np.ndarray, ratio: np.ndarray, max_rays: int) -> np.ndarray:
    """The rays a round of the adaptive budget extends each pulse to.

    ``done`` (n,) rays so far (multiples of :data:`BATCHES`, >= 2 x BATCHES); ``ratio`` (n,) the
    estimated error over the tolerance (> 1). The estimate scales as 1 / sqrt(N): the target is
    ``done x ratio^2``, at least one step and at most :data:`GROWTH` x ``done``, rounded up to a
    multiple of 2^(floor(log2 N) - log2 :data:`STEPS_PER_OCTAVE`) (overshoot <= 1 / STEPS_PER_OCTAVE
    of an octave's start), capped at ``max_rays``.
    """
    done = np.asarray(done, np.int64)
    need = np.minimum(done * np.asarray(ratio, np.float64) ** 2, GROWTH * done)
    need = np.maximum(need, done + 1)
    step = np.maximum(2 ** (np.floor(np.log2(need)).astype(np.int64) - int(math.log2(STEPS_PER_OCTAVE))), BATCHES)
    step = step // BATCHES * BATCHES
    return np.minimum(-(-need.astype(np.int64) // step) * step, max_rays).astype(np.int64)


def waveform_error(replicates: np.ndarray, kernel: np.ndarray, noise, bin_ns: float) -> np.ndarray:
    """Standard error of each pulse's recorded waveform, in noise SDs, from k estimates.

    Parameters
    ----------
    replicates : (n, k, n_bins) float64
        k unbiased estimates of each pulse's sigma(t) (k >= 2), independent or (batches of one
        scrambled Sobol' sequence) negatively correlated: the error of their mean is then overestimated.
    kernel : (n_k,) float64
        The system pulse on the sigma grid (``bin_ns``): the recorded waveform is kernel (x) sigma.
    noise : (n,) float64
        The digitiser's noise SD of each pulse, in the units of kernel (x) sigma.
    bin_ns : float

    Returns
    -------
    (n,) float64
        sqrt(mean over the samples of the support of Var(mean of the replicates)) / noise, the
        waveform sampled every :data:`ERROR_STEP_NS` ns (sigma summed over each step, the kernel
        point-sampled); the support: samples where the mean waveform reaches
        :data:`SUPPORT_SD` noise SDs (none: 0).
    """
    n, k, n_bins = replicates.shape
    step = max(1, int(round(ERROR_STEP_NS / bin_ns)))
    nc = n_bins // step
    coarse = replicates[:, :, :nc * step].reshape(n, k, nc, step).sum(axis=3)
    kc = np.asarray(kernel, np.float64)[::step]
    size = nc + kc.size - 1
    nfft = 1 << int(np.ceil(np.log2(size)))
    z = np.fft.irfft(np.fft.rfft(coarse, nfft, axis=2) * np.fft.rfft(kc, nfft)[None, None, :], nfft, axis=2)[..., :size]
    mean = z.mean(axis=1)
    var = z.var(axis=1, ddof=1) / k
    noise = np.asarray(noise, np.float64)
    support = mean >= SUPPORT_SD * noise[:, None]
    m = support.sum(axis=1)
    rms = np.sqrt(np.where(support, var, 0.0).sum(axis=1) / np.maximum(m, 1))
    return np.where(m > 0, rms / noise, 0.0)


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
          parallel: str = "pulses", progress: bool = False, survival=1.0, tolerance: float | None = None,
          min_rays: int = 1024, max_rays: int = 32768, kernel: np.ndarray | None = None,
          noise=None) -> TraceResult:
    """Forward Monte Carlo ray tracing of LiDAR pulses through a scene (docs/method.md §(d), Eq. 2).

    The ray budget: ``n_rays`` rays per pulse; or, with ``tolerance`` set, an adaptive budget
    per pulse between ``min_rays`` and ``max_rays`` that stops once the Monte Carlo standard
    error of the pulse's recorded waveform ``kernel (x) sigma`` falls to ``tolerance`` times its
    digitiser noise SD ``noise`` (RMS over the samples that carry signal, :func:`waveform_error`;
    docs/method.md §(d), "Ray budget"). ``n_rays`` is then unused. A caller that knows its sensor
    passes its system pulse S(t) on the sigma grid as ``kernel`` and, per pulse, the noise SD in
    the same units: for V = g S (x) sigma / R^2 + noise of SD s, ``noise = s R^2 / g``
    (:meth:`waveforest.model.forward.MCRTSetup.budget` computes both).

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
    tolerance : float, optional
        The adaptive budget's target: the recorded waveform's Monte Carlo SD as a fraction of
        the digitiser noise SD; None = ``n_rays`` rays per pulse.
    min_rays, max_rays : int
        Bounds of the adaptive budget, rays per pulse (each rounded down to a power of two).
    kernel : (n_k,) float64, optional
        The system pulse on the sigma grid (``bin_ns``), any units (adaptive budget only).
    noise : float or (n,) float64, optional
        Digitiser noise SD of each pulse in the units of ``kernel (x) sigma`` (adaptive budget only).

    Returns
    -------
    TraceResult
    """
    if not isinstance(beams, Beams):
        raise TypeError(f"beams: expected waveforest.mcrt.Beams, got {type(beams).__name__}")
    _check(n_rays, max_order, bin_ns, viewed_diameter_m, window_ns, specular, hotspot, sampler, roulette)
    adaptive = _adaptive(tolerance, min_rays, max_rays, kernel, noise, len(beams))
    st = _ChunkSettings(
        key=master_key(seed), n_rays=int(n_rays), max_order=int(max_order), bin_ns=float(bin_ns),
        n_bins=int(math.ceil(window_ns / bin_ns - 1e-9)), viewed_diameter_m=float(viewed_diameter_m),
        specular=float(specular), hotspot=float(hotspot), by_order=by_order, sampler=sampler,
        survive=survival_by_order(survival, max_order), roulette=float(roulette), adaptive=adaptive)
    planned = st.n_rays if adaptive is None else max(adaptive.min_rays, int(chunk_rays) // ADAPTIVE_CHUNK_PULSES)
    if isinstance(scene, PreparedScene):
        prepared = scene
    else:  # a HIGH-quality BVH pays for its longer build only over enough rays
        prepared = prepare(scene, quality=bvh_quality(len(beams), n_rays if adaptive is None else adaptive.min_rays))
    threads = default_threads() if threads is None else max(1, int(threads))
    chunks, by_pulses = _chunk_plan(len(beams), planned, int(chunk_rays), threads, parallel)
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
    rays = np.zeros(n, np.int64)
    error = np.full(n, np.nan)

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
        for i, (acc, drop, tot, fh, t0c, nr, err) in results:
            a, b = chunks[i]
            sigma[a:b], dropped[a:b], totals[a:b], first[a:b], t0[a:b], rays[a:b] = acc, drop, tot, fh, t0c, nr
            error[a:b] = err
    return TraceResult(
        sigma=sigma.sum(axis=1),
        t0_ns=t0,
        bin_ns=st.bin_ns,
        order_totals=totals,
        first_hit_counts=first,
        sigma_dropped=dropped,
        n_rays=st.n_rays if st.adaptive is None else int(rays.max(initial=0)),
        sigma_by_order=sigma if st.by_order else None,
        rays=rays,
        mc_error=error,
    )
