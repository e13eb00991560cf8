"""Peak resident memory and waveforms per second of the file commands on a large waveform file.

``--make SIZE_GB`` writes a LAS 1.4 point-format-9 file with its packets in a ``.wdp`` beside it
(16-bit samples at 1 ns) with the campaign writer (:class:`waveforest.io.las.write.WaveformLasWriter`):
the pulses of the bundled real RIEGL file (tests/data/real), repeated as tiles on a grid, each copy
with new GPS times, pulse ids and x/y offsets, until the LAS and ``.wdp`` reach SIZE_GB (1e9 bytes).

Then each command runs as a user types it (``ingest``, ``tune-cfd``, ``features --cfd``,
``quicklook``, and ``decompose`` where the tree has it, also with ``--point-format 9`` as
``decompose_pf9``), one fresh process each, under a small
parent that reports the child's peak RSS (``getrusage(RUSAGE_CHILDREN).ru_maxrss``). With
``--compare REF`` (default ``HEAD``) the same commands of ``git archive REF src`` run too, the two
taking turns command by command, so old and new are measured in one run.

Usage::

    python benchmarks/memory.py --make 1.0 [--dir /tmp/h47b]       # write big.las + big.wdp
    python benchmarks/memory.py [--dir /tmp/h47b] [--compare HEAD|none] [--commands ingest,...]

Figures, one a line: ``peak_rss_<command>[_<ref>]: N MB``, ``waveforms_per_s_<command>[_<ref>]: N /s``
(pulses over wall time), ``cpu_s_<command>[_<ref>]: N s``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

ROOT = Path(__file__).resolve().parents[1]
RIEGL = ROOT / "tests" / "data" / "real" / "riegl_fwf.las"
TILE_M = 32.0
"""Spacing of the copies of the RIEGL file's pulses (its footprint is ~28 m x 28 m)."""
GRID = 64
"""Tiles per row of the grid."""
COPIES_PER_CHUNK = 16
"""Copies of the base pulses per writer chunk (~38,000 pulses)."""

PARENT = r"""
import json, resource, subprocess, sys, time
t0 = time.perf_counter()
rc = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
wall = time.perf_counter() - t0
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
print(json.dumps(dict(rc=rc.returncode, err=rc.stderr[-2000:], wall=wall, cpu=ru.ru_utime + ru.ru_stime,
                      maxrss_mb=ru.ru_maxrss / 1024)))
"""


def _shift_list(col: pa.ChunkedArray, by: np.ndarray) -> pa.ListArray:
    """A list<float64> column with each row's values shifted by ``by[row]``."""
    arr = col.combine_chunks()
    off = arr.offsets.to_numpy().astype(np.int64)
    flat = arr.flatten().to_numpy() + np.repeat(by, np.diff(off))
    return pa.ListArray.from_arrays(pa.array(off.astype(np.int32)), pa.array(flat, pa.float64()))


def base_pulses() -> pa.Table:
    """The RIEGL file's pulses that the writer can hold (with a waveform and a DR echo)."""
    from waveforest.io.las.read import read_waveform_las

    t = read_waveform_las(RIEGL, agc_attribute=None)
    n_s = np.diff(t.column("samples").combine_chunks().offsets.to_numpy())
    keep = (n_s > 0) & (t.column("n_echoes").to_numpy() > 0)
    return t.filter(pa.array(keep))


def copies(base: pa.Table, first: int, count: int) -> pa.Table:
    """Copies ``first .. first + count - 1`` of ``base``: new GPS times, pulse ids and x/y offsets."""
    n = base.num_rows
    gps = base.column("gps_time").to_numpy()
    span = float(gps.max() - gps.min()) + 1e-3
    parts = []
    for k in range(first, first + count):
        dx, dy = (k % GRID) * TILE_M, (k // GRID) * TILE_M
        cols = {name: base.column(name) for name in base.column_names}
        cols["pulse_id"] = pa.array(np.arange(k * n, (k + 1) * n, dtype=np.int64))
        cols["gps_time"] = pa.array(gps + k * span)
        for axis, d in (("x", dx), ("y", dy)):
            for c in (f"anchor_{axis}", f"sensor_{axis}"):
                cols[c] = pa.array(base.column(c).to_numpy() + d)
            cols[f"echo_{axis}"] = _shift_list(base.column(f"echo_{axis}"), np.full(n, d))
        parts.append(pa.table(cols, schema=base.schema))
    return pa.concat_tables(parts)


def make(las: Path, size_gb: float) -> tuple[int, float]:
    """Write ``las`` (+ ``.wdp``) of about ``size_gb`` GB; return (pulses, seconds)."""
    from waveforest.io.las.write import WaveformLasWriter

    base = base_pulses()
    per_pulse = 120 + 59 * float(np.mean(base.column("n_echoes").to_numpy()))  # 60 16-bit samples + points
    n_copies = max(1, int(round(size_gb * 1e9 / (per_pulse * base.num_rows))))
    t0 = time.perf_counter()
    las.parent.mkdir(parents=True, exist_ok=True)
    with WaveformLasWriter(las, version="1.4", point_format=9, bits=16, storage="external", agc_attribute=None,
                           offsets=(548_000.0, 5_389_000.0, 0.0), system_identifier="benchmarks/memory.py") as w:
        for k in range(0, n_copies, COPIES_PER_CHUNK):
            w.write(copies(base, k, min(COPIES_PER_CHUNK, n_copies - k)))
            print(f"\rwrote {w.n_pulses:,} pulses", end="", file=sys.stderr)
    print(file=sys.stderr)
    return n_copies * base.num_rows, time.perf_counter() - t0


def has_decompose(src: Path) -> bool:
    return (src / "waveforest" / "stages" / "decompose.py").exists()


def commands(work: Path, las: Path, tag: str, src: Path) -> dict[str, list[str]]:
    """The command lines, outputs in ``work/tag``."""
    out = work / tag
    out.mkdir(parents=True, exist_ok=True)
    cli = [sys.executable, "-m", "waveforest.cli"]
    pulses, cfd, feats = out / "pulses.parquet", out / "cfd.json", out / "features.parquet"
    cmds = {
        "ingest": [*cli, "ingest", str(las), "--out", str(pulses), "--no-progress"],
        "tune_cfd": [*cli, "tune-cfd", str(pulses), "--out", str(cfd), "--plot", str(out / "cfd.png"), "--no-progress"],
        "features": [*cli, "features", str(pulses), "--cfd", str(cfd), "--out", str(feats), "--no-progress"],
        "quicklook": [*cli, "quicklook", str(las), "--out", str(out / "look"), "--force", "--no-progress"],
    }
    if has_decompose(src):
        cmds["decompose"] = [*cli, "decompose", str(las), "--out", str(out / "points.laz")]
        if "--point-format" in (src / "waveforest" / "stages" / "decompose.py").read_text():
            cmds["decompose_pf9"] = [*cli, "decompose", str(las), "--out", str(out / "points9.laz"),
                                     "--point-format", "9"]
    return cmds


def run(cmd: list[str], src: Path) -> dict:
    """Run one command in a fresh process whose parent reports its peak RSS, wall and CPU time."""
    env = dict(os.environ, PYTHONPATH=str(src))
    res = subprocess.run([sys.executable, "-c", PARENT, *cmd], env=env, capture_output=True, text=True, cwd=src.parent)
    rep = json.loads(res.stdout.strip().splitlines()[-1])
    if rep["rc"]:
        sys.exit(f"{' '.join(cmd)} failed ({rep['rc']}):\n{rep['err']}")
    return rep


def old_tree(ref: str, into: Path) -> Path:
    """``git archive ref src`` unpacked into ``into``; returns its src folder."""
    tar = subprocess.run(["git", "-C", str(ROOT), "archive", ref, "src"], capture_output=True, check=True).stdout
    into.mkdir(parents=True, exist_ok=True)
    tmp = into / "archive.tar"
    tmp.write_bytes(tar)
    with tarfile.open(tmp) as tf:
        tf.extractall(into, filter="data")
    tmp.unlink()
    return into / "src"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, default=Path("/tmp/h47b"), help="folder of big.las (default /tmp/h47b)")
    ap.add_argument("--make", type=float, default=None, metavar="SIZE_GB", help="write big.las (+ .wdp) of this size")
    ap.add_argument("--compare", default="HEAD", help="git ref to measure beside the working tree ('none': skip)")
    ap.add_argument("--commands", default=None, help="comma-separated subset (ingest,tune_cfd,features,quicklook,decompose,decompose_pf9)")
    args = ap.parse_args()
    las = args.dir / "big.las"
    if args.make is not None:
        n, s = make(las, args.make)
        size = las.stat().st_size + las.with_suffix(".wdp").stat().st_size
        print(f"file_size: {size / 1e9:.3f} GB")
        print(f"file_pulses: {n}")
        las.with_suffix(".json").write_text(json.dumps({"pulses": n, "bytes": size}))
        print(f"write_pulses_per_s: {n / s:.0f} /s")
        return
    if not las.with_suffix(".json").exists():
        sys.exit(f"{las}: no such file written by --make (write it with --make 1.0)")
    work = Path(tempfile.mkdtemp(prefix="memory-", dir=args.dir))
    try:
        trees = {"": ROOT / "src"}
        if args.compare != "none":
            trees[f"_{args.compare.lower()}"] = old_tree(args.compare, work / "old")
        lines = {tag: commands(work, las, tag.strip("_") or "new", src) for tag, src in trees.items()}
        wanted = args.commands.split(",") if args.commands else None
        n = json.loads(las.with_suffix(".json").read_text())["pulses"]
        for name in lines[""]:
            if wanted and name not in wanted:
                continue
            for tag, src in trees.items():
                if name not in lines[tag]:
                    continue
                rep = run(lines[tag][name], src)
                print(f"peak_rss_{name}{tag}: {rep['maxrss_mb']:.0f} MB")
                print(f"waveforms_per_s_{name}{tag}: {n / rep['wall']:.0f} /s")
                print(f"cpu_s_{name}{tag}: {rep['cpu']:.1f} s", flush=True)
        print(f"load_average_1min: {os.getloadavg()[0]:.2f} processes")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
