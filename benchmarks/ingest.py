"""Benchmark ``waveforest ingest`` on a generated LAS waveform file of at least 1 GB.

Writes a synthetic LAS 1.4 file (point format 9, 8-bit samples, 256 per packet, 1-3
returns per pulse, packets inside the file by default) with the streaming writer, then
ingests it in a fresh process pinned to one thread (Arrow CPU and I/O pools, Numba) and
reports throughput and peak resident memory. A second fresh process runs the reader
alone (no Parquet) to split the cost. Targets (issue 2): >= 200,000 pulses/s on one core,
peak RSS < 500 MB whatever the file size.

Usage::

    python benchmarks/ingest.py [--size-gb 1.05] [--dir DIR] [--storage internal|external] [--keep]

Each figure is printed on its own line as ``name: value unit``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test fixtures live in tests/fixtures

CHUNK_PULSES = 50_000

CHILD = r"""
import json, os, sys, time
os.environ["NUMBA_NUM_THREADS"] = "1"
import pyarrow as pa
pa.set_cpu_count(1)
pa.set_io_thread_count(1)
mode, las, out = sys.argv[1], sys.argv[2], sys.argv[3]
t0, c0 = time.perf_counter(), time.process_time()
if mode == "ingest":
    from waveforest.io.las.pulses import las_to_pulses
    n = las_to_pulses(las, out).n_pulses
else:
    from waveforest.io.las.read import WaveformPulseReader
    n = sum(t.num_rows for t in WaveformPulseReader(las))
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
# VmHWM: peak resident set of this process image (ru_maxrss would also count the parent's,
# which Linux carries over fork + exec)
hwm = next(int(l.split()[1]) for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps(dict(n=n, wall=wall, cpu=cpu, maxrss_mb=hwm / 1024)))
"""


def generate(path: Path, size_bytes: int, storage: str) -> tuple[int, float]:
    """Write synthetic pulses until the LAS (+ .wdp) reaches ``size_bytes``; return pulses, seconds."""
    from fixtures.pulses import synthetic_pulses

    from waveforest.io.las.write import WaveformLasWriter

    t0 = time.perf_counter()
    n = 0
    with WaveformLasWriter(path, storage=storage, offsets=(500_000.0, 6_800_000.0, 0.0)) as w:
        while w.n_points * w.dtype.itemsize + n * 256 < size_bytes:
            w.write(synthetic_pulses(CHUNK_PULSES, seed=n // CHUNK_PULSES, first_pulse_id=n, max_echoes=3))
            n += CHUNK_PULSES
    return n, time.perf_counter() - t0


def child(mode: str, las: Path, out: Path) -> dict:
    res = subprocess.run([sys.executable, "-c", CHILD, mode, str(las), str(out)], capture_output=True, text=True)
    if res.returncode:
        sys.exit(f"{mode} failed:\n{res.stderr}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size-gb", type=float, default=1.05, help="size of the generated LAS data, GB (1e9 bytes)")
    ap.add_argument("--dir", type=Path, default=None, help="working folder (default: a temporary one)")
    ap.add_argument("--storage", choices=["internal", "external"], default="internal")
    ap.add_argument("--keep", action="store_true", help="keep the generated files")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="waveforest-bench-ingest-", dir=args.dir))
    try:
        las = work / "bench.las"
        n, gen_s = generate(las, int(args.size_gb * 1e9), args.storage)
        size = las.stat().st_size + (las.with_suffix(".wdp").stat().st_size if args.storage == "external" else 0)
        print(f"file_size: {size / 1e9:.3f} GB")
        print(f"pulses: {n}")
        print(f"write_pulses_per_s: {n / gen_s:.0f} pulses/s")
        out = work / "pulses.parquet"
        ing = child("ingest", las, out)
        assert ing["n"] == n, (ing, n)
        print(f"ingest_pulses_per_s: {n / ing['wall']:.0f} pulses/s")
        print(f"ingest_pulses_per_cpu_s: {n / ing['cpu']:.0f} pulses/s")
        print(f"ingest_peak_rss: {ing['maxrss_mb']:.0f} MB")
        print(f"parquet_size: {out.stat().st_size / 1e9:.3f} GB")
        out.unlink()
        rd = child("read", las, out)
        print(f"read_only_pulses_per_s: {n / rd['wall']:.0f} pulses/s")
        print(f"read_only_pulses_per_cpu_s: {n / rd['cpu']:.0f} pulses/s")
        print(f"read_only_peak_rss: {rd['maxrss_mb']:.0f} MB")
        print(f"load_average_1min: {os.getloadavg()[0]:.2f} processes")
    finally:
        if args.keep:
            print(f"kept: {work}", file=sys.stderr)
        else:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
