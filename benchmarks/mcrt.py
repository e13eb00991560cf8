"""MCRT speed: ms per pulse on a 6 x 6 m random-leaf canopy and on the vegetation scenes, the
bare-Embree floor, scene build.

Scenes: the issue's canopy (LAI 3.35 of small leaves, spherical LAD, 6.7 cm^2 each, ~180,000
triangles, between 0 and 1.2 m over a ground) and the paper's three species built by
:func:`waveforest.vegetation.build_scene` (birch 3 m, raspberry 1.3 m, fireweed 1.5 m); pulses:
R = 1200 m, 0.15 mrad divergence (0.18 m footprint), scan zenith 0-15 deg, 30,000 rays,
10 orders (METHOD.md d).

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
  (:func:`waveforest.mcrt.tracer.bvh_quality`: HIGH from 12 pulses of 30,000 rays on);
* ``rays_per_pulse_intersect``, ``rays_per_pulse_occluded``: Embree work per pulse;
* ``trace_cpu_ms_per_pulse_serial``, ``embree_floor_cpu_ms_per_pulse_serial``,
  ``trace_over_floor_cpu``: the same on one thread, as CPU time of that thread, which other
  jobs on a shared machine disturb far less than wall time.

Wall times are the minimum of ``--repeat`` runs (the machine is shared). Run:
``python benchmarks/mcrt.py [--pulses 16] [--repeat 3] [--species birch raspberry fireweed]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numba
import numpy as np

from waveforest.mcrt import Beams, EmbreeIntersector, prepare, trace
from waveforest.mcrt.tracer import bvh_quality

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from fixtures.scenes import random_leaves

LAI, HEIGHT_M, SIZE_M, LEAF_AREA_M2 = 3.35, 1.2, 6.0, 6.7e-4
RANGE_M, DIVERGENCE_MRAD, MAX_ZENITH_DEG = 1200.0, 0.15, 15.0
N_RAYS, MAX_ORDER = 30000, 10


class Recorder:
    """An intersector wrapper that keeps every batch of rays it is asked to trace."""

    def __init__(self, inner):
        self.inner, self.backend = inner, inner.backend
        self.intersects, self.occludes = [], []

    def intersect(self, o, d, threads=None):
        self.intersects.append((o.copy(), d.copy()))
        return self.inner.intersect(o, d, threads=threads)

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


SPECIES = {"birch": 3.0, "raspberry": 1.3, "fireweed": 1.5}
"""The paper's species and the heights they are benchmarked at, m (as benchmarks/vegetation.py)."""


def bench_scene(prefix: str, scene, beams, args, full: bool) -> None:
    """Print the figures of one scene (names prefixed by ``prefix``)."""
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
    kw = dict(n_rays=N_RAYS, max_order=MAX_ORDER, seed=args.seed)
    trace(prepared, beams[:2], n_rays=500, max_order=3)  # compile / load the kernels

    modes = [("pulses", threads), ("rays", threads)] if threads > 1 else [("rays", 1)]
    if full and threads > 1:
        modes.append(("rays", 1))

    rec = Recorder(prepared.intersector)
    traced = type(prepared)(prepared.scene, rec, prepared.shift, prepared.tri_data, prepared.bounds)
    res = trace(traced, beams, threads=threads, parallel="rays", **kw)
    n_isect = sum(len(o) for o, _ in rec.intersects)
    n_occl = sum(len(o) for o, _, _ in rec.occludes)

    def replay(inner, thr):
        """Replay every recorded call: on ``thr`` worker threads (one Numba thread each, calls
        dealt out in turn, as ``trace(parallel="pulses")`` runs its chunks), or serially."""
        calls = [(inner.intersect, (o, d)) for o, d in rec.intersects]
        calls += [(inner.occluded, (o, d, t)) for o, d, t in rec.occludes]

        def part(k):
            numba.set_num_threads(1)
            for fn, a in calls[k::thr]:
                fn(*a, threads=1)

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
    for k in (1, 10, 30):  # the BVH quality that trace() picks for k pulses of one scene
        high = bvh_quality(k, kw["n_rays"]) == "high"
        amortised = (default + build / k) if high else (times["medium"] / n + build_medium / k)
        out(f"ms_per_pulse_amortised_{k}", amortised * 1e3, "ms")

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pulses", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--species", nargs="*", default=list(SPECIES), help="species to benchmark (none: canopy only)")
    args = ap.parse_args()
    print(f"cpu_count: {os.cpu_count()} cores")
    print(f"numba_threads: {numba.get_num_threads()} threads")
    print(f"load_average_1min: {os.getloadavg()[0]:.2f} processes")

    rng = np.random.default_rng(args.seed)
    n = args.pulses
    targets = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.zeros(n)])
    beams = Beams.toward(targets, RANGE_M, rng.uniform(0, MAX_ZENITH_DEG, n), rng.uniform(0, 360, n),
                         divergence_mrad=DIVERGENCE_MRAD)
    canopy = random_leaves(LAI, (0.0, HEIGHT_M), SIZE_M, LEAF_AREA_M2, seed=args.seed)
    bench_scene("", canopy, beams, args, full=True)
    if args.species:
        from waveforest.vegetation import build_scene

        for sp in args.species:
            bench_scene(f"{sp}_", build_scene(sp, SPECIES[sp], args.seed), beams, args, full=True)
    print(f"load_average_1min_end: {os.getloadavg()[0]:.2f} processes")


if __name__ == "__main__":
    main()
