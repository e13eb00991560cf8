"""Benchmark of `waveforest synthesize`: time to generate a virtual campaign.

Usage::

    python benchmarks/campaign.py                         # the test config (config/test/config.yaml)
    python benchmarks/campaign.py --config config/config.yaml   # the default study (all nine datasets)
    python benchmarks/campaign.py --config none           # built-in defaults

Prints one figure per line as ``name: value unit``: wall and CPU time (all threads; the site
loop runs ``--threads`` sites at a time), cores used (CPU / wall), pulses, LAS points, pulses per
second, sites, peak resident memory, and the stage times (``stage_scenes`` and ``stage_trace``
are summed over the worker threads; ``stage_sites_wall`` is the wall time of the site loop).
The machine is shared: compare ``synthesize_cpu`` between runs, or repeat. The budget of the issue: default
study <= 300 s, test config <= 30 s on the 2-core machine (tests never assert on time).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from waveforest import config
from waveforest.campaign import run
from waveforest.settings import campaign_settings

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "config" / "test" / "config.yaml"),
                    help="study config ('none' = built-in defaults)")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--effect", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--threads", type=int, default=None, help="sites traced at once / Numba threads (default: all cores)")
    ap.add_argument("--out", default=None, help="keep the campaign here (default: a temporary folder)")
    args = ap.parse_args(argv)
    cfg = config.load(None if args.config == "none" else args.config)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out) if args.out else Path(tmp) / "campaign"
        if args.threads:
            import numba

            numba.set_num_threads(args.threads)
        t0, c0 = time.perf_counter(), time.process_time()
        settings = campaign_settings(cfg)
        if args.seed is not None:
            settings = replace(settings, seed=args.seed)
        summary = run(settings, out, effects=args.effect, progress=False)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        size = sum(p.stat().st_size for p in out.iterdir()) / 1e6
    pulses = sum(summary.pulses.values())
    print(f"config: {args.config}")
    print(f"datasets: {len(summary.pulses)} count")
    print(f"synthesize_wall: {wall:.1f} s")
    print(f"synthesize_cpu: {cpu:.1f} s")
    print(f"cores_used: {cpu / wall:.2f} count")
    print(f"pulses: {pulses} count")
    print(f"las_points: {sum(summary.points.values())} count")
    print(f"pulses_per_s: {pulses / wall:.0f} 1/s")
    print(f"field_samples: {summary.n_fields} count")
    print(f"targets: {summary.n_targets} count")
    print(f"folder_size: {size:.1f} MB")
    for name, seconds in summary.timings.items():
        print(f"stage_{name}: {seconds:.1f} s")
    print(f"peak_rss: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
