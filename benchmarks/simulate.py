"""Benchmark of `waveforest simulate`: one chunk of a study, this source tree against another.

Usage::

    python benchmarks/simulate.py --results results [--dataset 2012_05_1] [--chunk 1]
        [--threads 2] [--baseline-src /path/to/old/src] [--repeat 1] [--config FILE]

``--results`` is a study's results folder after ``select`` and ``calibrate`` (e.g. of
``snakemake --cores 2``); the chunk is simulated by the CLI in a subprocess, with this tree's
``src`` and, given ``--baseline-src``, with that one, alternately (``--repeat`` rounds, the
shortest time kept), so both see the same machine load. Prints ``name: value unit``:
``simulate_wall_s``, ``simulate_cpu_s`` (all threads), ``simulate_pulses``,
``simulate_ms_per_pulse`` (wall), and with a baseline ``baseline_simulate_wall_s``,
``baseline_simulate_cpu_s`` and ``speedup`` (baseline wall / wall); ``same_table`` says whether
both wrote the same table (NaN equal to NaN). Use ``--repeat 2`` or more: each tree's first
run may compile its Numba kernels.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pyarrow.parquet as pq

from waveforest.io.pulses import same_table

ROOT = Path(__file__).resolve().parents[1]


def run_chunk(src: Path, args, out: Path) -> tuple[float, float]:
    """(wall s, CPU s of the child) of one ``waveforest simulate`` run with ``src`` first on the path."""
    r = Path(args.results)
    campaign = r / "campaign"
    cmd = [sys.executable, "-c", "from waveforest.cli import main; main()", "simulate", str(r / "select" / f"{args.dataset}.parquet"),
           "--fields", str(campaign / "fields.csv"), "--datasets", str(campaign / "datasets.csv"),
           "--system", str(r / "calibration" / f"{args.dataset}.parquet"),
           "--calibration", str(r / "calibration" / f"{args.dataset}.json"),
           "--chunk", str(args.chunk), "--chunks", str(args.chunks), "--out", str(out),
           "--threads", str(args.threads), "--config", str(args.config or r / "config" / "simulate.yaml")]
    env = dict(os.environ, PYTHONPATH=str(src))
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode(errors="replace")
    if proc.returncode != 0:
        sys.exit(f"simulate with {src} failed:\n{err[-2000:]}")
    return wall, usage.ru_utime + usage.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", required=True)
    ap.add_argument("--dataset", default="2012_05_1")
    ap.add_argument("--chunk", type=int, default=1)
    ap.add_argument("--chunks", type=int, default=4)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--baseline-src", default=None)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--config", default=None, help="study config (default: the results' config/simulate.yaml)")
    args = ap.parse_args()
    trees = {"": ROOT / "src"}
    if args.baseline_src:
        trees["baseline_"] = Path(args.baseline_src)
    best: dict[str, tuple[float, float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        outs = {k: Path(tmp) / f"{k or 'this'}.parquet" for k in trees}
        for _ in range(args.repeat):
            for k, src in trees.items():
                wall, cpu = run_chunk(src, args, outs[k])
                if k not in best or wall < best[k][0]:
                    best[k] = (wall, cpu)
        n = pq.read_metadata(outs[""]).num_rows
        for k, (wall, cpu) in best.items():
            print(f"{k}simulate_wall_s: {wall:.1f} s")
            print(f"{k}simulate_cpu_s: {cpu:.1f} s")
        print(f"simulate_pulses: {n} pulses")
        print(f"simulate_ms_per_pulse: {best[''][0] / max(n, 1) * 1e3:.1f} ms")
        if "baseline_" in best:
            print(f"speedup: {best['baseline_'][0] / best[''][0]:.2f} x")
            same = same_table(pq.read_table(outs[""]), pq.read_table(outs["baseline_"]))
            print(f"same_table: {int(same)} bool")


if __name__ == "__main__":
    main()
