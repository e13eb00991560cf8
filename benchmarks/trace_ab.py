"""The tracer's CPU per pulse in this checkout against another one's, in one run.

Each round runs one subprocess per tree, one after the other (the order alternating between
rounds), on the same plants (birch 4 m, raspberry 1.2 m, fireweed 1.5 m, seed 7) and the same
16 nadir pulses: first order only and 10 orders, 16,384 Sobol' rays with roulette 0.5, one
thread. Per tree the median over rounds of the CPU per pulse; the sum of sigma tells whether the
two trees trace the same result.

Usage::

    git worktree add /tmp/base <commit>
    python benchmarks/trace_ab.py --baseline-src /tmp/base/src [--rounds 3]

Prints ``name: value unit`` lines: ``trace_ms_per_pulse_<species>_o<orders>`` (this tree),
``baseline_trace_ms_per_pulse_...``, ``speedup_<species>_o<orders>`` (baseline / this) and
``same_sigma`` (1 if every sigma sum agrees to the last bit).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

SRC = str(Path(__file__).resolve().parents[1] / "src")

CHILD = r"""
import json, time, numpy as np
from waveforest.vegetation import build
from waveforest.mcrt import Beams, prepare, trace
rng = np.random.default_rng(3)
n = 16
xy = rng.uniform(-0.4, 0.4, (n, 2))
beams = Beams(np.column_stack([xy, np.full(n, 1100.0)]), np.tile([0.0, 0.0, -1.0], (n, 1)), np.full(n, 0.2))
out = {}
for sp, h in (("birch", 4.0), ("raspberry", 1.2), ("fireweed", 1.5)):
    ps = prepare(build(sp, h, 7).scene)
    trace(ps, beams, 1024, 10, seed=5, sampler="sobol", roulette=0.5, threads=1)  # compile, warm caches
    for orders in (1, 10):
        t0 = time.process_time()
        r = trace(ps, beams, 16384, orders, seed=5, sampler="sobol", roulette=0.5, threads=1)
        out[f"{sp}_o{orders}"] = [(time.process_time() - t0) / n * 1e3, float(r.sigma.sum())]
print(json.dumps(out))
"""


def run(src: str) -> dict:
    env = {**os.environ, "PYTHONPATH": src, "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline-src", required=True, help="src folder of the other checkout")
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    this, base = [], []
    for k in range(a.rounds):
        for tree in ((SRC, this), (a.baseline_src, base))[:: 1 if k % 2 == 0 else -1]:
            tree[1].append(run(tree[0]))
    same = all(r[key][1] == b[key][1] for r in this for b in base for key in r)
    for key in this[0]:
        mine = float(np.median([r[key][0] for r in this]))
        other = float(np.median([r[key][0] for r in base]))
        print(f"trace_ms_per_pulse_{key}: {mine:.2f} ms")
        print(f"baseline_trace_ms_per_pulse_{key}: {other:.2f} ms")
        print(f"speedup_{key}: {other / mine:.3f} x")
    print(f"same_sigma: {int(same)}")


if __name__ == "__main__":
    main()
