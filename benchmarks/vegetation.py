"""Vegetation build speed and size: prints one figure per line as ``name: value unit``.

Usage: python benchmarks/vegetation.py [--repeats N]

For the paper's three species at typical heights (birch 3 m, raspberry 1.3 m, fireweed 1.5 m)
it reports the median wall time and process CPU time of ``build_scene`` (after one warm-up
call that compiles the Numba kernels; the target is <= 50 ms per birch or raspberry plot),
and the triangle counts by kind. CPU time is the better figure on a shared machine.

With ``--bvh`` it also reports, per species, the CPU time of making each instance ready to
trace (:func:`waveforest.mcrt.prepare`: per-triangle records and the Embree BVH) at each build
quality (``prepare_<species>_cpu_<quality>``): with the generation, the cost of a new
instance per pulse (issue 27).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from waveforest.vegetation import build_scene

CASES = (("birch", 3.0), ("raspberry", 1.3), ("fireweed", 1.5))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=11, help="timed builds per species")
    ap.add_argument("--bvh", action="store_true", help="also time prepare() at each BVH quality")
    args = ap.parse_args(argv)
    for species, height in CASES:
        build_scene(species, height, 0)  # warm-up: Numba compile / cache load
        wall, cpu = [], []
        for seed in range(1, args.repeats + 1):
            w0, c0 = time.perf_counter(), time.process_time()
            scene = build_scene(species, height, seed)
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
        counts = np.bincount(scene.kind, minlength=4)
        print(f"build_{species}: {1e3 * np.median(wall):.1f} ms")
        print(f"build_{species}_cpu: {1e3 * np.median(cpu):.1f} ms")
        print(f"{species}_triangles: {len(scene)} triangles")
        print(f"{species}_leaf_triangles: {counts[1]} triangles")
        print(f"{species}_wood_triangles: {counts[2]} triangles")
        if args.bvh:
            from waveforest.mcrt import prepare

            for quality in ("low", "medium", "high"):
                prepare(scene, quality=quality)  # warm-up
                cpu = []
                for _ in range(max(3, args.repeats // 2)):
                    c0 = time.process_time()
                    prepare(scene, quality=quality)
                    cpu.append(time.process_time() - c0)
                print(f"prepare_{species}_cpu_{quality}: {1e3 * np.median(cpu):.1f} ms")


if __name__ == "__main__":
    main()
