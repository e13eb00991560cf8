"""MCRT speed: ms per pulse on a 6 x 6 m random-leaf canopy and on the vegetation scenes, the
bare-Embree floor, scene build; Monte Carlo error in sigma(t) and where the sensor sees it.

Scenes: the issue's canopy (LAI 3.35 of small leaves, spherical LAD, 6.7 cm^2 each, ~180,000
triangles, between 0 and 1.2 m over a ground) and the paper's three species built by
:func:`waveforest.vegetation.build_scene` (birch 3 m, raspberry 1.3 m, fireweed 1.5 m); pulses:
R = 1200 m, 0.15 mrad divergence (0.18 m footprint), scan zenith 0-15 deg, 30,000 rays,
10 orders (docs/method.md §(d)).

Figures (``name: value unit``), canopy first, then ``<species>_...`` for each species:

* ``scene_triangles``, ``scene_build_ms`` (Embree BVH of HIGH quality and per-triangle arrays,
  :func:`prepare`); ``scene_build_ms_medium`` (MEDIUM quality) and ``trace_ms_per_pulse_medium``
  (the default trace on it);
* ``trace_ms_per_pulse[_<mode>_<threads>]`` for each way of using the threads (the first is the
  default of :func:`trace`); ``mrays_per_s``: Embree rays (intersect + occlusion) per second
  of the default trace;
* ``embree_floor_ms_per_pulse``: the same rays (recorded during a trace) replayed through the
  bare Embree calls (of :mod:`waveforest.mcrt.backends.embree`, so in its Z-order), intersect + occlusion,
  the calls dealt out to one worker thread per core; ``trace_over_floor``: the ratio
  (target <= 2); ``embreex_floor_ms_per_pulse``: the same rays through embreex's ``run``
  (split over Python threads), the path the tracer used before :mod:`waveforest.mcrt.backends.embree`;
* ``ms_per_pulse_amortised_<k>``: tracing plus the scene build shared by k pulses (a pool of
  instances; target <= 100 ms), on the BVH quality :func:`trace` builds for k pulses
  (:func:`waveforest.mcrt.tracer.bvh_quality`: HIGH from 12 pulses of 30,000 rays on); for
  the canopy, ``ms_per_pulse_amortised_1`` is that of a canopy assembled anew for every
  pulse from a library of leaf bricks (below), ``ms_per_pulse_amortised_1_flat`` that of a
  new flat canopy (one BVH over all its triangles);
* canopy only, a new canopy per pulse from bricks (:func:`bench_bricks`): the 6 x 6 m
  canopy as 3 x 3 bricks of 2 m drawn from a library of :data:`BRICKS` independent
  ``random_leaves`` bricks (HIGH BVHs, built once: ``brick_library_build_ms``), each turned
  by a multiple of 90 deg (``tests/fixtures/scenes.py:brick_canopy``), on a two-level BVH
  (:func:`waveforest.mcrt.prepare_instances`): ``scene_build_ms_instanced`` (one
  arrangement), ``trace_ms_per_pulse_instanced`` (all pulses on one arrangement), and
  ``ms_per_pulse_amortised_1``: every pulse on its own new arrangement, arrangement and
  trace of a pulse as one unit on each core (:func:`waveforest.workers.unordered_map`);
* ``rays_per_pulse_intersect``, ``rays_per_pulse_occluded``: Embree work per pulse;
* ``trace_cpu_ms_per_pulse_serial``, ``embree_floor_cpu_ms_per_pulse_serial``,
  ``trace_over_floor_cpu``: the same on one thread, as CPU time of that thread, which other
  jobs on a shared machine disturb far less than wall time.

Monte Carlo error (``--sections error``; :func:`bench_error`), per scene at a fixed instance and
``--error-pulses`` fixed pulses, for the default tracer (``random_30k``: 30,000 pseudo-random
rays) and each estimator of :data:`METHODS`, over ``--seeds`` seeds, each against a reference
of :data:`REF_RAYS` rays of the same instance and pulses (the ``sobol`` sampler, the most
accurate per ray; its own error is << that of the estimators):

* ``<method>_rel_rms_1ns``: relative RMS error of sigma(t) summed to 1-ns bins,
  sqrt(mean over seeds of sum_bins (s - s_ref)^2 / sum_bins s_ref^2), averaged over pulses;
* ``<method>_rel_err_total``, ``<method>_rel_err_order1``: relative RMS error of the total
  and of the first-order sigma;
* ``<method>_rel_err_apeak``, ``<method>_rel_err_e``, ``<method>_err_fwhm``: the errors of the
  first-echo features of the noise-free waveform recorded with a Gaussian S(t) of 7.2 ns FWHM
  (2010_12_1), sampled at 1 ns (:func:`recorded`: the study's first echo, the segment at 3
  noise SDs); FWHM in ns;
* ``<method>_err_share_order1``, ``..._order2``, ``..._order3plus``: each order's squared
  error (sum over seeds, pulses and 1-ns bins of (s_k - s_k,ref)^2) over that of the total:
  where the error lies (their sum differs from 1 by the orders' cross terms);
* ``<method>_cpu_ms_per_pulse``: CPU time per pulse of the method's traces on one thread
  (median over the seeds: threads that wait for a core of a loaded machine burn CPU time and
  disturb the comparison), on the BVH quality of the method (:data:`METHODS`);
  ``<method>_embree_rays_per_pulse``;
* ``<method>_efficiency_vs_random_30k``: (e_old^2 t_old) / (e_new^2 t_new) with e the
  ``rel_rms_1ns`` error and t the CPU time: the time the default estimator needs for the
  new one's error (its variance falls as 1 / rays) over the new one's time;
* ``<method>_ms_per_pulse_amortised_1``: a new instance per pulse: build of the BVH the
  method is meant for (:data:`METHODS`) plus its trace, CPU ms; ``..._efficiency_amortised_1``
  the same ratio with the build included on both sides (the default on a MEDIUM BVH);
* the headline ``efficiency_vs_random_30k`` of :data:`RECOMMENDED`, with its
  ``recommended_cpu_ms_per_pulse_amortised_1`` and ``recommended_n_rays``.

The error where the sensor sees it (``--sections sensor``; :func:`bench_sensor`), per scene on
``--error-pulses`` fixed pulses of a fixed instance over ``--seeds`` seeds, for
:data:`SENSOR_METHODS` (or ``--methods``): the recorded waveform's Monte Carlo error in digitiser
noise SDs (``<m>_wave_err_rms``, ``_p95``, ``_frac_below_third``), the Monte Carlo SD of Apeak, E
and FWHM over their SD between :data:`INSTANCES` plant instances, rays and CPU per pulse, and
each efficiency against ``random_30k`` with a bootstrap 95 % interval over the seeds.

Control variates across neighbouring pulses (``--sections neighbours``; :func:`bench_neighbours`):
the correlation of the recorded waveform's Monte Carlo error between two pulses whose beams are
``NEIGHBOUR_OFFSETS_M`` apart and share their random numbers (the same seed and pulse index:
``neighbours_corr_<dx>m``), against two independent seeds (``neighbours_corr_independent_<dx>m``),
and ``neighbours_cv_gain_<dx>m`` = 1 / (1 - rho^2), the most a control variate built on the
neighbour (its expectation known exactly) could divide the variance by.

The virtual campaign's Monte Carlo noise (``--sections campaign``; :func:`bench_campaign`): fixed
ray counts (``--campaign-rays``) and its adaptive budget at ``--campaign-tolerances``, against the
true sensor's digitiser noise.

The speed section traces with the settings of ``--method`` (default :data:`RECOMMENDED`, the
tracer's default in the study config; the flat ``ms_per_pulse_amortised_1`` uses the method's
one-pulse BVH quality) and prints its ``n_rays`` (unused by an adaptive method) and
``traced_rays_per_pulse``.

Wall times are the minimum of ``--repeat`` runs (the machine is shared). Run:
``python benchmarks/mcrt.py [--pulses 16] [--repeat 3] [--species birch raspberry fireweed]
[--sections speed error sensor neighbours campaign] [--quick]``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np

from waveforest.mcrt import Beams, EmbreeIntersector, prepare, prepare_instances, prepare_prototypes, trace
from waveforest.mcrt.tracer import bvh_quality
from waveforest.workers import unordered_map

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from fixtures.scenes import brick_canopy, leaf_bricks, plane, random_leaves

LAI, HEIGHT_M, SIZE_M, LEAF_AREA_M2 = 3.35, 1.2, 6.0, 6.7e-4
RANGE_M, DIVERGENCE_MRAD, MAX_ZENITH_DEG = 1200.0, 0.15, 15.0
N_RAYS, MAX_ORDER = 30000, 10


class Recorder:
    """An intersector wrapper that keeps every batch of rays it is asked to trace."""

    def __init__(self, inner):
        self.inner, self.backend = inner, inner.backend
        self.intersects, self.occludes = [], []

    def intersect(self, o, d, threads=None, coherent=False):
        self.intersects.append((o.copy(), d.copy(), coherent))
        return self.inner.intersect(o, d, threads=threads, coherent=coherent)

    def occluded(self, o, d, t, threads=None):
        self.occludes.append((o.copy(), d.copy(), np.array(t, np.float32)))
        return self.inner.occluded(o, d, t, threads=threads)


def interleaved(fns: dict, repeat: int, clock=time.perf_counter) -> dict:
    """Shortest time of each of ``fns`` over ``repeat`` rounds that run each once, s."""
    times = {k: float("inf") for k in fns}
    for _ in range(repeat):
        for k, fn in fns.items():
            t = clock()
            fn()
            times[k] = min(times[k], clock() - t)
    return times


def best(fn, repeat: int, clock=time.perf_counter) -> float:
    """Shortest of ``repeat`` runs of ``fn`` on ``clock``, s."""
    times = []
    for _ in range(repeat):
        t = clock()
        fn()
        times.append(clock() - t)
    return min(times)


REF_RAYS = 2**20
"""Rays of the reference sigma(t) of the error section (1,048,576, sampler ``sobol``)."""

METHODS = {
    "random_30k": dict(n_rays=30000, sampler="random", roulette=0.0, quality="medium"),
    "random_16k": dict(n_rays=16384, sampler="random", roulette=0.0, quality="medium"),
    "random_rr_30k": dict(n_rays=30000, sampler="random", roulette=0.5, quality="medium"),
    "sobol_16k": dict(n_rays=16384, sampler="sobol", roulette=0.0, quality="medium"),
    "sobol_rr_8k": dict(n_rays=8192, sampler="sobol", roulette=0.5, quality="medium"),
    "sobol_rr_12k": dict(n_rays=12288, sampler="sobol", roulette=0.5, quality="medium"),
    "sobol_rr_16k": dict(n_rays=16384, sampler="sobol", roulette=0.5, quality="medium"),
    "sobol_rr_16k_low": dict(n_rays=16384, sampler="sobol", roulette=0.5, quality="low"),
    "sobol_rr_24k": dict(n_rays=24576, sampler="sobol", roulette=0.5, quality="medium"),
    "sobol_rr_32k": dict(n_rays=32768, sampler="sobol", roulette=0.5, quality="medium"),
    "random_1500": dict(n_rays=1500, sampler="random", roulette=0.0, quality="medium"),
    "sobol_rr_256": dict(n_rays=256, sampler="sobol", roulette=0.5, quality="medium"),
    "sobol_rr_512": dict(n_rays=512, sampler="sobol", roulette=0.5, quality="medium"),
    "sobol_rr_768": dict(n_rays=768, sampler="sobol", roulette=0.5, quality="medium"),
    "adaptive_0.33": dict(n_rays=16384, sampler="sobol", roulette=0.5, quality="medium", tolerance=1 / 3),
    "adaptive_0.25": dict(n_rays=16384, sampler="sobol", roulette=0.5, quality="medium", tolerance=0.25),
    "adaptive_0.2": dict(n_rays=16384, sampler="sobol", roulette=0.5, quality="medium", tolerance=0.2),
    "adaptive_0.2_b8": dict(n_rays=16384, sampler="sobol", roulette=0.5, quality="medium", tolerance=0.2, batches=8),
}
"""Estimators of the error section: ``trace`` keywords, and the BVH quality a one-pulse
instance gets (``quality``). ``random_30k`` was the default before ``sobol_rr_16k``;
``random_1500`` was the virtual campaign's own tracing before ``sobol_rr_512``; ``adaptive_<tol>``:
the adaptive ray budget (``trace(tolerance=...)``, :func:`trace_kwargs`) at that fraction of the
digitiser noise SD :data:`NOISE_SD_DN` of the waveform of S(t) :data:`SYSTEM_FWHM_NS`, :data:`SYSTEM_PEAK`
(``n_rays`` unused); ``_b8``: its error estimated from 8 batches instead of
:data:`waveforest.mcrt.tracer.BATCHES` (the earlier estimator; :func:`batches`)."""

SENSOR_METHODS = ("random_30k", "sobol_rr_16k", "adaptive_0.25", "adaptive_0.2_b8", "adaptive_0.2")
"""Estimators of the sensor section (:func:`bench_sensor`): the paper's, today's fixed default, the adaptive budgets."""

NOISE_SD_DN = 1.3
"""Digitiser noise SD of the sensor section and of the adaptive methods, DN (2010_12_1)."""

INSTANCES = 8
"""Plant instances per scene whose spread sets the features' between-instance SD (sensor section)."""

BOOTSTRAP = 2000
"""Bootstrap resamples of the seeds for the efficiencies' 95 % intervals."""

QUICK_METHODS = ("random_30k", "sobol_16k", "sobol_rr_12k", "sobol_rr_16k")

RECOMMENDED = "adaptive_0.2"
"""The method of the headline figures: the study's default (``mcrt.tolerance`` 0.2)."""

SYSTEM_FWHM_NS, SYSTEM_PEAK = 7.2, 1.5e9
"""Gaussian S(t) of the feature errors: 2010_12_1's pulse width; peak in DN m^2 per unit
sigma (a rho = 0.3 plane at 1200 m gives ~100 DN)."""

BRICKS, BRICK_M = 36, 2.0
"""Leaf bricks in the canopy's library, and their side (3 x 3 bricks make the 6 x 6 m canopy)."""

SPECIES = {"birch": 3.0, "raspberry": 1.3, "fireweed": 1.5}
"""The paper's species and the heights they are benchmarked at, m (as benchmarks/vegetation.py)."""


@contextlib.contextmanager
def batches(method: dict):
    """The adaptive budget's batch count of a :data:`METHODS` entry (``batches``; default: the tracer's)."""
    import waveforest.mcrt.tracer as tracer

    kept = tracer.BATCHES
    tracer.BATCHES = method.get("batches", kept)
    try:
        yield
    finally:
        tracer.BATCHES = kept


def trace_kwargs(method: dict, n: int | None = None) -> dict:
    """``trace`` keywords of a :data:`METHODS` entry (its ``quality`` and ``batches`` left out); an adaptive one
    gets the system pulse and noise (:data:`SYSTEM_PEAK`, :data:`NOISE_SD_DN` at :data:`RANGE_M`)."""
    kw = {k: v for k, v in method.items() if k not in ("quality", "batches")}
    if kw.get("tolerance") is not None:
        from waveforest.sensor.system_waveform import gaussian_system_waveform

        kw.update(kernel=gaussian_system_waveform(SYSTEM_FWHM_NS, SYSTEM_PEAK).s, noise=NOISE_SD_DN * RANGE_M**2)
    return kw


def bench_bricks(beams, kw: dict, args, out) -> None:
    """The canopy assembled anew for every pulse from a library of leaf bricks (module docstring)."""
    threads = numba.get_num_threads()
    rng = np.random.default_rng(args.seed)
    t = time.perf_counter()
    parts = leaf_bricks(BRICKS, LAI, (0.0, HEIGHT_M), BRICK_M, LEAF_AREA_M2, seed=args.seed)
    protos = prepare_prototypes(parts + [plane(SIZE_M, 0.0, 0.3)])
    out("brick_library_build_ms", (time.perf_counter() - t) * 1e3, "ms")
    per_side = int(round(SIZE_M / BRICK_M))

    def arrange(r):
        return prepare_instances(protos, *brick_canopy(BRICKS, per_side, BRICK_M, r))

    arrange(rng)
    out("scene_build_ms_instanced", best(lambda: arrange(rng), args.repeat) * 1e3, "ms")
    one = arrange(rng)
    trace(one, beams[:2], n_rays=500, max_order=3, sampler="random", roulette=0.0)  # warm-up
    out("trace_ms_per_pulse_instanced", best(lambda: trace(one, beams, threads=threads, **kw), args.repeat)
        / len(beams) * 1e3, "ms")
    streams = np.random.SeedSequence(args.seed).spawn(len(beams))

    def unit(i):  # pulse i on its own new arrangement (seeded by the pulse)
        return trace(arrange(np.random.default_rng(streams[i])), beams[i:i + 1], threads=1, **kw).total[0]

    def run():
        return sum(v for _, v in unordered_map(unit, list(range(len(beams))), threads))

    out("ms_per_pulse_amortised_1", best(run, args.repeat) / len(beams) * 1e3, "ms")


def bench_scene(prefix: str, scene, beams, args, full: bool, bricks: bool = False) -> None:
    """Print the figures of one scene (names prefixed by ``prefix``); ``bricks``: also those of
    :func:`bench_bricks` (the canopy)."""
    threads = numba.get_num_threads()
    n = len(beams)

    def out(name: str, value: float, unit: str, fmt: str = ".1f") -> None:
        print(f"{prefix}{name}: {value:{fmt}} {unit}")

    out("scene_triangles", len(scene), "triangles", "d")
    prepared = prepare(scene)  # warm-up (Embree device, kernels)
    build = best(lambda: prepare(scene), args.repeat)
    out("scene_build_ms", build * 1e3, "ms")
    build_medium = best(lambda: prepare(scene, quality="medium"), args.repeat)
    out("scene_build_ms_medium", build_medium * 1e3, "ms")
    medium = prepare(scene, quality="medium")
    q1 = METHODS[args.method]["quality"]  # the BVH of a one-pulse instance
    kw = dict(max_order=MAX_ORDER, seed=args.seed, **trace_kwargs(METHODS[args.method]))
    out("n_rays", kw["n_rays"], "rays", "d")
    if q1 not in ("medium", "high"):
        build_one = best(lambda: prepare(scene, quality=q1), args.repeat)
        out(f"scene_build_ms_{q1}", build_one * 1e3, "ms")
        one = prepare(scene, quality=q1)
    trace(prepared, beams[:2], n_rays=500, max_order=3, sampler="random", roulette=0.0)  # compile / load the kernels

    modes = [("pulses", threads), ("rays", threads)] if threads > 1 else [("rays", 1)]
    if full and threads > 1:
        modes.append(("rays", 1))

    rec = Recorder(prepared.intersector)
    traced = type(prepared)(prepared.scene, rec, prepared.shift, prepared.tri_data, prepared.bounds)
    res = trace(traced, beams, threads=threads, parallel="rays", **kw)
    out("traced_rays_per_pulse", float(res.rays.mean()), "rays")
    n_isect = sum(len(o) for o, _, _ in rec.intersects)
    n_occl = sum(len(o) for o, _, _ in rec.occludes)

    def replay(inner, thr):
        """Replay every recorded call: on ``thr`` worker threads (one Numba thread each, calls
        dealt out in turn, as ``trace(parallel="pulses")`` runs its chunks), or serially."""
        calls = [(inner.intersect, (o, d), {"coherent": c}) for o, d, c in rec.intersects]
        calls += [(inner.occluded, (o, d, t), {}) for o, d, t in rec.occludes]

        def part(k):
            numba.set_num_threads(1)
            for fn, a, kw in calls[k::thr]:
                fn(*a, threads=1, **kw)

        def run():
            if thr == 1:
                part(0)
                return
            with ThreadPoolExecutor(thr) as pool:
                list(pool.map(part, range(thr)))
        return run

    embreex = EmbreeIntersector((prepared.scene.triangles.astype(np.float64) - prepared.shift).astype(np.float32))
    # every round runs every variant once, so that all see the same load of the shared machine
    fns = {(mode, thr): (lambda mode=mode, thr=thr: trace(prepared, beams, threads=thr, parallel=mode, **kw))
           for mode, thr in modes}
    fns["medium"] = lambda: trace(medium, beams, threads=threads, parallel=modes[0][0], **kw)
    if q1 not in ("medium", "high"):
        fns[q1] = lambda: trace(one, beams, threads=threads, parallel=modes[0][0], **kw)
    fns["floor"] = replay(prepared.intersector, threads)
    fns["embreex"] = replay(embreex, threads)
    times = interleaved(fns, args.repeat)
    per_pulse = {k: times[k] / n for k in modes}
    default = per_pulse[modes[0]]
    floor = times["floor"] / n
    out("trace_ms_per_pulse", default * 1e3, "ms")
    for (mode, thr), v in per_pulse.items():
        out(f"trace_ms_per_pulse_{mode}_{thr}threads", v * 1e3, "ms")
    out("mrays_per_s", (n_isect + n_occl) / (default * n) / 1e6, "Mrays/s", ".2f")
    out("embree_floor_ms_per_pulse", floor * 1e3, "ms")
    out("trace_over_floor", default / floor, "x", ".2f")
    out("embreex_floor_ms_per_pulse", times["embreex"] / n * 1e3, "ms")
    out("rays_per_pulse_intersect", n_isect / n, "rays", ".0f")
    out("rays_per_pulse_occluded", n_occl / n, "rays", ".0f")
    out("trace_ms_per_pulse_medium", times["medium"] / n * 1e3, "ms")
    if q1 not in ("medium", "high"):
        out(f"trace_ms_per_pulse_{q1}", times[q1] / n * 1e3, "ms")
    for k in (1, 10, 30):  # the BVH quality that trace() picks for k pulses of one scene
        high = bvh_quality(k, kw["n_rays"]) == "high"
        amortised = (default + build / k) if high else (times["medium"] / n + build_medium / k)
        if k == 1 and q1 not in ("medium", "high"):  # the method's one-pulse BVH
            amortised = times[q1] / n + build_one
        out(f"ms_per_pulse_amortised_{k}{'_flat' if k == 1 and bricks else ''}", amortised * 1e3, "ms")
    if bricks:
        bench_bricks(beams, kw, args, out)

    if full:  # one thread, CPU time of this thread (robust to other jobs on the machine)
        prev = numba.get_num_threads()
        numba.set_num_threads(1)
        try:
            cpu_t = interleaved({"trace": lambda: trace(prepared, beams, threads=1, parallel="rays", **kw),
                                 "floor": replay(prepared.intersector, 1)}, args.repeat, time.thread_time)
            cpu, cpu_floor = cpu_t["trace"] / n, cpu_t["floor"] / n
        finally:
            numba.set_num_threads(prev)
        out("trace_cpu_ms_per_pulse_serial", cpu * 1e3, "ms")
        out("embree_floor_cpu_ms_per_pulse_serial", cpu_floor * 1e3, "ms")
        out("trace_over_floor_cpu", cpu / cpu_floor, "x", ".2f")
    out("mean_sigma_total", res.total.mean(), "per sr", ".4f")
    out("mean_order1_fraction", (res.order_totals[:, 0] / res.total).mean(), "fraction", ".3f")


def _one_ns(res) -> np.ndarray:
    """(n, layers, n_ns) sigma summed to 1-ns bins (bins of 0.05 ns, 20 per ns)."""
    s = res.sigma_by_order
    k = int(round(1.0 / res.bin_ns))
    n_ns = s.shape[2] // k
    return s[:, :, :n_ns * k].reshape(s.shape[0], s.shape[1], n_ns, k).sum(axis=3)


def bench_error(prefix: str, scene, beams, args, methods) -> dict:
    """Print the Monte Carlo errors of ``methods`` on one scene (see the module docstring).

    Returns {method: (rel_rms_1ns, cpu_s_per_pulse, build_cpu_s)}.
    """
    def out(name: str, value: float, unit: str, fmt: str = ".4f") -> None:
        print(f"{prefix}{name}: {value:{fmt}} {unit}", flush=True)

    n = len(beams)
    prepared = prepare(scene, quality="high")
    trace(prepared, beams[:1], n_rays=256, max_order=3, sampler="sobol", roulette=0.5)  # compile
    ref_res = trace(prepared, beams, n_rays=REF_RAYS, sampler="sobol", roulette=0.0, seed=10**6, by_order=True,
                    max_order=MAX_ORDER)
    ref = _one_ns(ref_res)
    ref_all, ref_1 = ref.sum(axis=1), ref[:, 0]
    ref_feat = recorded(ref_res)[1]
    builds = {}
    for q in {m["quality"] for m in methods.values()}:
        builds[q] = best(lambda q=q: prepare(scene, quality=q), max(3, args.repeat), time.process_time)
        out(f"scene_build_cpu_ms_{q}", builds[q] * 1e3, "ms", ".1f")

    class Counter:
        def __init__(self, inner):
            self.inner, self.backend, self.rays = inner, inner.backend, 0

        def intersect(self, o, d, threads=None, coherent=False):
            self.rays += len(o)
            return self.inner.intersect(o, d, threads=threads, coherent=coherent)

        def occluded(self, o, d, t, threads=None):
            self.rays += len(o)
            return self.inner.occluded(o, d, t, threads=threads)

    counted = {}  # the BVH each method is meant for, its Embree calls counted
    for q in builds:
        pq = prepared if q == "high" else prepare(scene, quality=q)
        counted[q] = type(pq)(pq.scene, Counter(pq.intersector), pq.shift, pq.tri_data, pq.bounds)
    found = {}
    # seeds outermost, methods inner: every method sees the same load of the shared machine
    sig = {m: [] for m in methods}
    feat = {m: [] for m in methods}
    cpu = {m: [] for m in methods}
    rays = dict.fromkeys(methods, 0)
    for seed in range(args.seeds):
        for m, kw in methods.items():
            tkw = trace_kwargs(kw)
            target = counted[kw["quality"]]
            target.intersector.rays = 0
            with batches(kw):
                c = time.process_time()
                res = trace(target, beams, seed=seed, by_order=True, max_order=MAX_ORDER, threads=1, **tkw)
                cpu[m].append(time.process_time() - c)
            rays[m] += target.intersector.rays
            sig[m].append(_one_ns(res))
            feat[m].append(recorded(res)[1])
    for m, kw in methods.items():
        s = np.array(sig[m])  # (seeds, n, orders, n_ns)
        d_all = s.sum(axis=2) - ref_all[None]
        rel_rms = float(np.mean(np.sqrt((d_all**2).sum(axis=2).mean(axis=0) / (ref_all**2).sum(axis=1))))
        rel_tot = float(np.mean(np.sqrt((d_all.sum(axis=2)**2).mean(axis=0)) / ref_all.sum(axis=1)))
        d_1 = s[:, :, 0].sum(axis=2) - ref_1.sum(axis=1)[None]
        rel_1 = float(np.mean(np.sqrt((d_1**2).mean(axis=0)) / ref_1.sum(axis=1)))
        f = np.array(feat[m])  # (seeds, n, 3)
        df = f - ref_feat[None]
        rel_ap = float(np.mean(np.sqrt((df[..., 0]**2).mean(axis=0)) / ref_feat[:, 0]))
        rel_e = float(np.mean(np.sqrt((df[..., 1]**2).mean(axis=0)) / ref_feat[:, 1]))
        err_fwhm = float(np.mean(np.sqrt((df[..., 2]**2).mean(axis=0))))
        t = float(np.median(cpu[m])) / n
        found[m] = (rel_rms, t, builds[kw["quality"]])
        out(f"{m}_n_rays", kw["n_rays"], "rays", "d")
        out(f"{m}_rel_rms_1ns", rel_rms, "fraction")
        out(f"{m}_rel_err_total", rel_tot, "fraction")
        out(f"{m}_rel_err_order1", rel_1, "fraction")
        out(f"{m}_rel_err_apeak", rel_ap, "fraction")
        out(f"{m}_rel_err_e", rel_e, "fraction")
        out(f"{m}_err_fwhm", err_fwhm, "ns")
        d_k = s - ref[None]  # per order: its share of the squared error (cross terms aside)
        sq_k = (d_k**2).sum(axis=(0, 1, 3)) / (d_all**2).sum()
        out(f"{m}_err_share_order1", sq_k[0], "fraction", ".3f")
        out(f"{m}_err_share_order2", sq_k[1], "fraction", ".3f")
        out(f"{m}_err_share_order3plus", sq_k[2:].sum(), "fraction", ".3f")
        out(f"{m}_cpu_ms_per_pulse", t * 1e3, "ms", ".1f")
        out(f"{m}_embree_rays_per_pulse", rays[m] / (args.seeds * n), "rays", ".0f")
    base = "random_30k" if "random_30k" in found else "random_1500" if "random_1500" in found else None
    if base is None:
        return found
    e0, t0, b0 = found[base]
    for m, (e, t, b) in found.items():
        if base != "random_30k":
            out(f"{m}_efficiency_vs_{base}", (e0**2 * t0) / (e**2 * t), "x", ".2f")
            continue
        out(f"{m}_efficiency_vs_random_30k", (e0**2 * t0) / (e**2 * t), "x", ".2f")
        out(f"{m}_ms_per_pulse_amortised_1", (t + b) * 1e3, "ms", ".1f")
        out(f"{m}_efficiency_amortised_1", (e0**2 / e**2 * t0 + b0) / (t + b), "x", ".2f")
    if RECOMMENDED in found:
        e, t, b = found[RECOMMENDED]
        print(f"{prefix}recommended_method: {RECOMMENDED}")
        out("efficiency_vs_random_30k", (e0**2 * t0) / (e**2 * t), "x", ".2f")
        out("recommended_cpu_ms_per_pulse_amortised_1", (t + b) * 1e3, "ms", ".1f")
        if methods[RECOMMENDED].get("tolerance") is None:  # an adaptive budget's rays vary by pulse
            out("recommended_n_rays", methods[RECOMMENDED]["n_rays"], "rays", "d")
    return found


def recorded(res, noise_sd: float = NOISE_SD_DN) -> tuple[np.ndarray, np.ndarray]:
    """The noise-free recorded waveforms of ``res`` (Eq. 7 with the Gaussian S(t) of
    :data:`SYSTEM_FWHM_NS`, :data:`SYSTEM_PEAK` at R = :data:`RANGE_M`, sampled every 1 ns), DN,
    and their first-echo features (n, 3) Apeak (DN), E (DN), FWHM (ns) as the study finds them:
    :func:`waveforest.model.forward.noise_free_waveforms`, the segment at 3 ``noise_sd``."""
    from waveforest.model.forward import noise_free_waveforms
    from waveforest.sensor.system_waveform import gaussian_system_waveform

    system = gaussian_system_waveform(SYSTEM_FWHM_NS, SYSTEM_PEAK)
    _, _, w, f = noise_free_waveforms(res.sigma, res.t0_ns, res.bin_ns, system, noise_sd, RANGE_M)
    return w, np.column_stack([f["Apeak"], f["E"], f["FWHM"]])


def boot_ratio(a: np.ndarray, b: np.ndarray, cost_a: float, cost_b: float, rng) -> tuple[float, float, float]:
    """Efficiency (mean a x cost_a) / (mean b x cost_b) of per-seed squared errors ``a``, ``b``
    (same seeds), and its bootstrap 95 % interval over the seeds (paired resampling)."""
    est = (a.mean() * cost_a) / (b.mean() * cost_b)
    idx = rng.integers(0, a.size, (BOOTSTRAP, a.size))
    r = (a[idx].mean(axis=1) * cost_a) / np.maximum(b[idx].mean(axis=1) * cost_b, 1e-300)
    lo, hi = np.percentile(r, [2.5, 97.5])
    return float(est), float(lo), float(hi)


def bench_sensor(prefix: str, scene, instance, beams, args, methods) -> dict:
    """The Monte Carlo error where the sensor sees it (``--sections sensor``), on one scene.

    For ``methods`` over ``--seeds`` seeds at a fixed instance and pulses, against a reference of
    :data:`REF_RAYS` rays: the recorded waveform's error e (per pulse and seed: RMS over the
    1-ns samples where the reference waveform reaches 0.1 noise SD, of the difference, in noise
    SDs :data:`NOISE_SD_DN`: ``<m>_wave_err_rms`` its RMS, ``<m>_wave_err_p95`` its 95th
    percentile, ``<m>_wave_frac_below_third`` the share of pulse-seeds below 1/3); the Monte
    Carlo SD of Apeak, E (relative) and FWHM (ns) and each over the SD between
    :data:`INSTANCES` plant instances (``instance(k)``: the scene of instance k) at the same
    pulses (``<m>_<f>_mc_over_instance_sd``); CPU per pulse (one thread, median over the seeds),
    rays per pulse; efficiencies (err^2 x CPU of random_30k over the method's) for the waveform
    and each feature with a bootstrap 95 % interval over the seeds (``..._lo95``, ``..._hi95``).
    """
    def out(name: str, value: float, unit: str, fmt: str = ".4f") -> None:
        print(f"{prefix}{name}: {value:{fmt}} {unit}", flush=True)

    n = len(beams)
    prepared = prepare(scene, quality="high")
    trace(prepared, beams[:1], n_rays=256, max_order=3, sampler="sobol", roulette=0.5)  # compile
    ref_res = trace(prepared, beams, n_rays=REF_RAYS, sampler="sobol", roulette=0.0, seed=10**6,
                    max_order=MAX_ORDER)
    w_ref, f_ref = recorded(ref_res)
    support = w_ref >= 0.1 * NOISE_SD_DN
    inst = []  # features of each instance (a fixed estimator, its MC spread << the instances')
    for k in range(INSTANCES):
        r = trace(instance(k), beams, seed=k, max_order=MAX_ORDER, **trace_kwargs(METHODS["sobol_rr_16k"]))
        inst.append(recorded(r)[1])
    inst_sd = np.nanstd(np.array(inst), axis=0, ddof=1)  # (n, 3)
    for j, name in enumerate(("apeak", "e", "fwhm")):
        unit = "ns" if name == "fwhm" else "fraction"
        val = np.nanmean(inst_sd[:, j] if name == "fwhm" else inst_sd[:, j] / f_ref[:, j])
        out(f"instance_sd_{name}", val, unit)
    out("reference_apeak_dn", float(np.mean(f_ref[:, 0])), "DN", ".1f")
    medium = prepare(scene, quality="medium")
    err2 = {m: [] for m in methods}  # per seed: mean over pulses of e^2
    ferr2 = {m: [] for m in methods}  # per seed: (3,) mean over pulses of the features' squared errors
    allerr = {m: [] for m in methods}
    cpu = {m: [] for m in methods}
    rays = {m: [] for m in methods}
    for seed in range(args.seeds):  # seeds outermost: every method sees the same load
        for m in methods:
            with batches(METHODS[m]):
                c = time.thread_time()
                res = trace(medium, beams, seed=seed, max_order=MAX_ORDER, threads=1, **trace_kwargs(METHODS[m]))
                cpu[m].append(time.thread_time() - c)
            rays[m].append(res.rays.mean())
            w, f = recorded(res)
            e = np.sqrt(np.where(support, (w - w_ref) ** 2, 0).sum(axis=1) / np.maximum(support.sum(axis=1), 1))
            e = e / NOISE_SD_DN
            allerr[m].extend(e.tolist())
            err2[m].append(np.mean(e**2))
            d = f - f_ref
            d[:, :2] /= f_ref[:, :2]
            ferr2[m].append(np.nanmean(d**2, axis=0))
    rng = np.random.default_rng(0)
    base = "random_30k" if "random_30k" in methods else None
    found = {}
    for m in methods:
        e2, fe2 = np.array(err2[m]), np.array(ferr2[m])
        t = float(np.median(cpu[m])) / n
        found[m] = (e2, fe2, t)
        out(f"{m}_rays_per_pulse", float(np.mean(rays[m])), "rays", ".0f")
        out(f"{m}_cpu_ms_per_pulse", t * 1e3, "ms", ".1f")
        a = np.array(allerr[m])
        out(f"{m}_wave_err_rms", float(np.sqrt(np.mean(a**2))), "noise_sd")
        out(f"{m}_wave_err_p95", float(np.percentile(a, 95)), "noise_sd")
        out(f"{m}_wave_frac_below_third", float(np.mean(a < 1 / 3)), "fraction", ".3f")
        for j, name in enumerate(("apeak", "e", "fwhm")):
            sd = np.sqrt(fe2[:, j].mean())
            out(f"{m}_{name}_mc_sd", sd, "ns" if name == "fwhm" else "fraction")
            rel = inst_sd[:, j] if name == "fwhm" else inst_sd[:, j] / f_ref[:, j]
            out(f"{m}_{name}_mc_over_instance_sd", sd / float(np.nanmean(rel)), "ratio")
    if base is None:
        return found
    b2, bf2, tb = found[base]
    for m, (e2, fe2, t) in found.items():
        if m == base:
            continue
        for name, a, b in [("wave", b2, e2)] + [(q, bf2[:, j], fe2[:, j]) for j, q in enumerate(("apeak", "e", "fwhm"))]:
            est, lo, hi = boot_ratio(a, b, tb, t, rng)
            out(f"{m}_eff_{name}_vs_{base}", est, "x", ".2f")
            out(f"{m}_eff_{name}_vs_{base}_lo95", lo, "x", ".2f")
            out(f"{m}_eff_{name}_vs_{base}_hi95", hi, "x", ".2f")
    return found


NEIGHBOUR_OFFSETS_M = (0.01, 0.02, 0.05, 0.1, 0.2)
"""Distances between the two beams of the neighbours section, m (the canopy's leaves are 2.6 cm)."""


def bench_neighbours(prefix: str, scene, beams, args) -> None:
    """Correlation of two neighbouring pulses' Monte Carlo errors under common random numbers
    (``--sections neighbours``): for each offset, the recorded waveforms' errors (against
    :data:`REF_RAYS`-ray references) of ``beams`` and of the same beams moved by the offset,
    traced with the default's 16,384 Sobol' rays and roulette (a fixed count, so that every ray
    has its twin) over ``--seeds`` seeds, correlated over seeds, pulses and samples; and the same
    with the moved beams on other seeds (independent, the estimate's own noise)."""
    prepared = prepare(scene, quality="high")
    kw = dict(max_order=MAX_ORDER, **trace_kwargs(METHODS["sobol_rr_16k"]))

    def reference(b):
        return recorded(trace(prepared, b, n_rays=REF_RAYS, sampler="sobol", roulette=0.0, seed=10**6,
                              max_order=MAX_ORDER))[0]

    def errors(b, ref, first_seed):
        return np.array([recorded(trace(prepared, b, seed=first_seed + s, **kw))[0] - ref for s in range(args.seeds)])

    def corr(a, b):
        return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))

    ref0 = reference(beams)
    err0 = errors(beams, ref0, 0)  # the unmoved beams: the same for every offset
    for dx in NEIGHBOUR_OFFSETS_M:
        moved = Beams(beams.origin + np.array([dx, 0.0, 0.0]), beams.direction, beams.footprint_m, beams.range_m)
        ref1 = reference(moved)
        support = (ref0 >= 0.1 * NOISE_SD_DN) | (ref1 >= 0.1 * NOISE_SD_DN)
        a, b, c = (np.where(support, e, 0.0) for e in (err0, errors(moved, ref1, 0), errors(moved, ref1, 10**4)))
        rho = corr(a, b)
        print(f"{prefix}neighbours_corr_{dx:g}m: {rho:.3f} ratio", flush=True)
        print(f"{prefix}neighbours_corr_independent_{dx:g}m: {corr(a, c):.3f} ratio", flush=True)
        print(f"{prefix}neighbours_cv_gain_{dx:g}m: {1.0 / (1.0 - rho**2):.3f} x", flush=True)


CAMPAIGN_DATASET = "2010_12_1"
"""The dataset whose true sensor the campaign section records with."""


def bench_campaign(prefix: str, scene, beams, args) -> None:
    """The virtual campaign's Monte Carlo noise against its digitiser noise (``--sections campaign``).

    The field-sample pulses of ``beams`` on a fixed instance, traced as the campaign traces them
    (:func:`waveforest.campaign.site_trace.site_budget`, the true sensor of
    :data:`CAMPAIGN_DATASET`, R = :data:`RANGE_M`, recorded at the gain the budget assumes,
    :data:`waveforest.campaign.site_trace.AGC_HIGH_SD` SDs of the terrain level above its mean) over ``--seeds`` seeds, with each fixed count of
    ``--campaign-rays`` and the adaptive budget (from 256 rays) at each of ``--campaign-tolerances``: ``campaign_<tol>_wave_err_rms`` (RMS over pulses and seeds
    of the recorded waveform's error against a reference of :data:`REF_RAYS` rays, RMS over the
    samples with signal, in noise SDs), ``..._p95``, ``..._rays_per_pulse``, ``..._cpu_ms_per_pulse``.
    """
    from waveforest.campaign.params import load_datasets
    from waveforest.campaign.site_trace import AGC_HIGH_SD, SiteJob, TraceSettings, site_budget
    from waveforest.campaign.truth_sensor import TruthSensor
    from waveforest.sensor.signal import analog_waveforms

    sensor = TruthSensor.from_row(load_datasets([CAMPAIGN_DATASET]).iloc[0])
    n = len(beams)
    job = SiteJob("bench", "sample", "", 0.0, 0.0, 0.0, 0.0, 0.0, beams.origin, beams.direction,
                  np.full(n, DIVERGENCE_MRAD), np.full(n, RANGE_M), np.zeros(n, np.int64), np.arange(n))
    g = float(sensor.agc.gain(sensor.agc.bg_mean + AGC_HIGH_SD * sensor.agc.bg_sd))
    system = sensor.system_waveform()

    def wave(res):
        v, _ = analog_waveforms(res.sigma, res.t0_ns, RANGE_M, system, gain=np.full(n, g), bin_ns=res.bin_ns)
        return v[:, ::int(round(sensor.sampling_ns / res.bin_ns))]

    prepared = prepare(scene, quality="medium")
    w_ref = wave(trace(prepared, beams, n_rays=REF_RAYS, sampler="sobol", roulette=0.0, seed=10**6,
                       max_order=MAX_ORDER))
    support = w_ref >= 0.1 * sensor.noise_sd_dn
    print(f"{prefix}campaign_peak_dn: {w_ref.max(axis=1).mean():.1f} DN")
    for fixed, tol in [(k, None) for k in args.campaign_rays] + [(256, t) for t in args.campaign_tolerances]:
        st = TraceSettings(seed=0, n_rays=fixed, max_order=MAX_ORDER, viewed_diameter_m=5.0, specular=0.0,
                           hotspot=1.0, trigger_loss=0.0, ground_rho=0.3, lai_jitter=0.0, vegetation_effects=(),
                           sensors=(sensor,), bvh_quality="medium", sampler="sobol", roulette=0.5,
                           tolerance=tol, max_rays=32768)
        errs, cpu, rays = [], [], []
        for seed in range(args.seeds):
            c = time.thread_time()
            res = trace(prepared, beams, n_rays=fixed, max_order=MAX_ORDER, seed=seed, sampler="sobol", roulette=0.5,
                        threads=1, **site_budget(job, st))
            cpu.append(time.thread_time() - c)
            rays.append(res.rays.mean())
            d = np.where(support, (wave(res) - w_ref) ** 2, 0.0).sum(axis=1) / np.maximum(support.sum(axis=1), 1)
            errs.extend((np.sqrt(d) / sensor.noise_sd_dn).tolist())
        e = np.array(errs)
        name = f"campaign_fixed{fixed}" if tol is None else f"campaign_{tol:g}"
        print(f"{prefix}{name}_wave_err_rms: {np.sqrt(np.mean(e**2)):.3f} noise_sd")
        print(f"{prefix}{name}_wave_err_p95: {np.percentile(e, 95):.3f} noise_sd")
        print(f"{prefix}{name}_rays_per_pulse: {np.mean(rays):.0f} rays")
        print(f"{prefix}{name}_cpu_ms_per_pulse: {np.median(cpu) / n * 1e3:.1f} ms", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pulses", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--species", nargs="*", default=list(SPECIES), help="species to benchmark (none: canopy only)")
    ap.add_argument("--sections", nargs="+", default=["speed", "error"], choices=["speed", "error", "sensor", "neighbours", "campaign"])
    ap.add_argument("--campaign-rays", type=int, nargs="+", default=[256, 1024],
                    help="campaign section: fixed ray counts (default 256 1024)")
    ap.add_argument("--campaign-tolerances", type=float, nargs="*", default=[0.33, 0.2, 0.1],
                    help="adaptive tolerances of the campaign section")
    ap.add_argument("--method", default=RECOMMENDED, choices=list(METHODS),
                    help="tracer settings of the speed section (default: the study's default)")
    ap.add_argument("--seeds", type=int, default=16, help="seeds per method in the error section")
    ap.add_argument("--error-pulses", type=int, default=4, help="fixed pulses per scene in the error section")
    ap.add_argument("--methods", nargs="+", choices=list(METHODS), default=None,
                    help="estimators of the error section (default: all, or QUICK_METHODS with --quick)")
    ap.add_argument("--quick", action="store_true",
                    help="error section only, canopy only, the methods of QUICK_METHODS")
    args = ap.parse_args()
    if args.quick:
        args.sections, args.species = ["error"], []
    print(f"cpu_count: {os.cpu_count()} cores")
    print(f"numba_threads: {numba.get_num_threads()} threads")
    print(f"load_average_1min: {os.getloadavg()[0]:.2f} processes")

    rng = np.random.default_rng(args.seed)
    n = args.pulses
    targets = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.zeros(n)])
    beams = Beams.toward(targets, RANGE_M, rng.uniform(0, MAX_ZENITH_DEG, n), rng.uniform(0, 360, n),
                         divergence_mrad=DIVERGENCE_MRAD)
    canopy = random_leaves(LAI, (0.0, HEIGHT_M), SIZE_M, LEAF_AREA_M2, seed=args.seed)
    scenes = {"": canopy}
    if args.species:
        from waveforest.vegetation import build_scene

        scenes.update({f"{sp}_": build_scene(sp, SPECIES[sp], args.seed) for sp in args.species})
    methods = {m: METHODS[m] for m in (args.methods or (QUICK_METHODS if args.quick else METHODS))}
    builders = {"": lambda k: random_leaves(LAI, (0.0, HEIGHT_M), SIZE_M, LEAF_AREA_M2, seed=args.seed + 1 + k)}
    for sp in args.species:
        from waveforest.vegetation import build_scene

        builders[f"{sp}_"] = lambda k, sp=sp: build_scene(sp, SPECIES[sp], args.seed + 1 + k)
    for prefix, scene in scenes.items():
        if "speed" in args.sections:
            bench_scene(prefix, scene, beams, args, full=True, bricks=prefix == "")
        if "error" in args.sections:
            eb = beams[:args.error_pulses]
            if prefix == "birch_":  # pulses through the crown (as tests/test_vegetation_mcrt.py)
                eb = Beams.toward(0.3 * targets[:args.error_pulses], RANGE_M, 0.0, 0.0,
                                  divergence_mrad=DIVERGENCE_MRAD)
            bench_error(prefix, scene, eb, args, methods)
        if "sensor" in args.sections:
            eb = beams[:args.error_pulses]
            if prefix == "birch_":
                eb = Beams.toward(0.3 * targets[:args.error_pulses], RANGE_M, 0.0, 0.0,
                                  divergence_mrad=DIVERGENCE_MRAD)
            bench_sensor(prefix, scene, builders[prefix], eb, args,
                         [m for m in (args.methods or SENSOR_METHODS)])
        if "neighbours" in args.sections:
            bench_neighbours(prefix, scene, beams[:args.error_pulses], args)
        if "campaign" in args.sections:
            bench_campaign(prefix, scene, beams[:args.error_pulses], args)
    print(f"load_average_1min_end: {os.getloadavg()[0]:.2f} processes")


if __name__ == "__main__":
    main()
