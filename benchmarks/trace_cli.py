"""The tracer through its commands, against a frozen copy of an earlier waveforest, in one run.

For one vegetation instance (``waveforest vegetation``, timed for each copy, with its picture),
every copy traces the same PLY with ``waveforest trace`` at its own defaults, once per seed,
each call a new process as a user runs it, the copies taking turns. Figures (``name: value unit``), ``<tag>`` being
``old`` (the frozen copy) or ``new`` (this checkout):

* ``<tag>_n_rays``: rays per pulse of the copy's default;
* ``<tag>_vegetation_s``: wall time of the ``vegetation`` command;
* ``<tag>_trace_wall_s``: median wall time of a ``trace`` command (start-up included);
* ``<tag>_trace_stage_s``: median time ``trace`` reports for its work (read, BVH, trace, write);
* ``<tag>_rel_spread_1ns``: spread of sigma(t) over seeds in 1-ns bins,
  sqrt(sum_bins var_seeds / sum_bins mean^2) (both copies are unbiased: this is their error);
* ``efficiency_stage``, ``efficiency_wall``, ``efficiency_pulse``: (e_old^2 t_old) /
  (e_new^2 t_new) with t the stage time, the command's wall time, and the wall time of
  ``vegetation`` + ``trace`` (a new instance per pulse, as the paper traces).

Run: ``python benchmarks/trace_cli.py [--old-commit 1c67060 | --old-src PATH] [--species
raspberry] [--height 1.3] [--seeds 16]``. ``--old-commit`` checks the commit out into a
temporary git worktree (removed at the end); 1c67060 is the tracer before issue 27.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

ROOT = Path(__file__).resolve().parents[1]

CONSOLE_SCRIPT = "import waveforest.cli as c; (getattr(c, 'entry', None) or c.main)()"
"""What the ``waveforest`` console script runs, in either copy (``main`` before ``entry``)."""


def command(src: Path, *args: str) -> tuple[str, float]:
    """Run ``waveforest ARGS`` from the source tree ``src`` in a new process, as its console
    script does: (stdout, wall s)."""
    env = dict(os.environ, PYTHONPATH=str(src))
    t = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", CONSOLE_SCRIPT, *args],
                       env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if r.returncode:
        sys.exit(f"waveforest {' '.join(args)} ({src}) failed:\n{r.stderr}")
    return r.stdout, wall


def sigma_1ns(path: Path) -> np.ndarray:
    """sigma(t) of a ``trace`` output summed to 1-ns bins of its own grid."""
    t = pq.read_table(path, columns=["time_ns", "sigma"]).to_pandas()
    return np.bincount(np.floor(t["time_ns"] - t["time_ns"].iloc[0] + 1e-9).astype(int), weights=t["sigma"])


def measure(copies: dict[str, Path], scene: Path, work: Path, args) -> dict[str, tuple[float, float, float, float]]:
    """Print each copy's figures: {tag: (rel_spread, stage s, wall s, vegetation s)}. The copies
    take turns command by command, so that both see the same load of a shared machine."""
    veg, sig, stage, wall, rays = {}, {}, {}, {}, {}
    for tag, src in copies.items():
        _, veg[tag] = command(src, "vegetation", "--species", args.species, "--height", str(args.height),
                              "--seed", "3", "--out", str(work / f"{tag}.ply"))
        command(src, "trace", str(scene), "--out", str(work / f"{tag}_warm.parquet"))  # Numba caches
        sig[tag], stage[tag], wall[tag] = [], [], []
    for seed in range(args.seeds):
        for tag, src in copies.items():
            out = work / f"{tag}_{seed}.parquet"
            text, w = command(src, "trace", str(scene), "--out", str(out), "--seed", str(seed))
            n, t = re.search(r"(\d+) rays", text), re.search(r" ([0-9.]+) s(?:;|$)", text.strip())
            rays[tag] = int(n.group(1))
            sig[tag].append(sigma_1ns(out))
            stage[tag].append(float(t.group(1)))
            wall[tag].append(w)
    found = {}
    for tag in copies:
        n = max(len(s) for s in sig[tag])
        a = np.array([np.pad(s, (0, n - len(s))) for s in sig[tag]])
        spread = float(np.sqrt(a.var(axis=0, ddof=1).sum() / (a.mean(axis=0) ** 2).sum()))
        found[tag] = (spread, float(np.median(stage[tag])), float(np.median(wall[tag])), veg[tag])
        print(f"{tag}_n_rays: {rays[tag]} rays")
        print(f"{tag}_vegetation_s: {veg[tag]:.2f} s")
        print(f"{tag}_trace_wall_s: {found[tag][2]:.3f} s")
        print(f"{tag}_trace_stage_s: {found[tag][1]:.3f} s")
        print(f"{tag}_rel_spread_1ns: {spread:.4f} fraction", flush=True)
    return found


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    old = ap.add_mutually_exclusive_group()
    old.add_argument("--old-commit", default="1c67060", help="commit of the frozen copy (a worktree of this repository)")
    old.add_argument("--old-src", type=Path, help="src/ folder of a frozen copy instead of --old-commit")
    ap.add_argument("--species", default="raspberry")
    ap.add_argument("--height", type=float, default=1.3)
    ap.add_argument("--seeds", type=int, default=16)
    args = ap.parse_args()
    print(f"load_average_1min: {os.getloadavg()[0]:.2f} processes")
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        tree = work / "old"
        if args.old_src is None:
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), args.old_commit],
                           check=True, capture_output=True)
        try:
            old_src = args.old_src or tree / "src"
            new_src = ROOT / "src"
            scene = work / "scene.ply"
            command(new_src, "vegetation", "--species", args.species, "--height", str(args.height),
                    "--seed", "3", "--out", str(scene), "--no-png")
            found = measure({"old": old_src, "new": new_src}, scene, work, args)
            (e0, s0, w0, v0), (e1, s1, w1, v1) = found["old"], found["new"]
        finally:
            if args.old_src is None:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)],
                               capture_output=True)
    ratio = e0**2 / e1**2
    print(f"efficiency_stage: {ratio * s0 / s1:.2f} x")
    print(f"efficiency_wall: {ratio * w0 / w1:.2f} x")
    print(f"efficiency_pulse: {ratio * (w0 + v0) / (w1 + v1):.2f} x")
    print(f"load_average_1min_end: {os.getloadavg()[0]:.2f} processes")


if __name__ == "__main__":
    main()
