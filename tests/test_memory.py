"""Memory stays bounded on large waveform files: what a command holds grows far slower than the file.

A fresh process ingests and tunes the CFD of two files written by ``benchmarks/memory.py`` (the real
RIEGL pulses repeated), ~5 MB and ~50 MB (after a warm-up run), and measures each step's peak resident memory above
the resident memory before it (Linux ``VmHWM``, reset through ``/proc/self/clear_refs``). The
constant part (imports, compiled kernels, one batch) cancels in the difference between the two
files; for tune-cfd the difference must stay far below the difference of the file sizes (holding
the pulses, or a few float64 arrays per pulse, breaks it); ingest, whose bound is its bucket of
points, must stay under a fixed bound.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from waveforest.cli import main

ROOT = Path(__file__).resolve().parents[1]
RIEGL = ROOT / "tests" / "data" / "real" / "riegl_fwf.las"

GROWTH_PER_FILE_BYTE = 0.25
"""Largest allowed growth of a step's peak memory per byte of extra input file. The RIEGL pulses
take ~183 bytes each (60 16-bit samples and their points); tune-cfd keeps ~30 bytes per pulse
for its check and plot (~0.16), and holding the pulses' arrays as before (~90 bytes) fails."""
INGEST_GROWTH_BYTES = 100e6
"""Largest allowed peak growth of ingest on the ~50-MB file (its pulse table as Arrow arrays would
take more than twice the file)."""
BUCKET_POINTS = 20_000
"""Ingest's points grouped at once, below both files' point counts, so that both stream."""

CHILD = r"""
import importlib.util, json, sys
from pathlib import Path
spec = importlib.util.spec_from_file_location("memory_benchmark", sys.argv[1])
bench = importlib.util.module_from_spec(spec)
spec.loader.exec_module(bench)
from waveforest import config, settings
from waveforest.io.las.pulses import las_to_pulses
from waveforest.model.self_tuning import tune_pulse_table

def status(key):
    return next(int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith(key + ":"))

def growth(step):
    with open("/proc/self/clear_refs", "w") as fh:  # the peak (VmHWM) restarts from the current RSS
        fh.write("5")
    before = status("VmRSS")
    step()
    return status("VmHWM") - before

work, bucket = Path(sys.argv[2]), int(sys.argv[3])
s = settings.self_tuning_settings(config.load(None))
out = {}
for name, gb in (("warm-up", 0.005), ("small", 0.005), ("large", 0.05)):
    las = work / name / "big.las"
    bench.make(las, gb)
    pulses = work / name / "pulses.parquet"
    out[name] = {
        "bytes": las.stat().st_size + las.with_suffix(".wdp").stat().st_size,
        "ingest": growth(lambda: las_to_pulses(las, pulses, agc_attribute=None, bucket_points=bucket)),
        "tune_cfd": growth(lambda: tune_pulse_table(pulses, s, progress=False)),
    }
print(json.dumps(out))
"""


def test_peak_memory_grows_far_slower_than_the_file(tmp_path):
    if not Path("/proc/self/clear_refs").exists():
        pytest.skip("needs Linux /proc/self/clear_refs to reset the peak RSS")
    res = subprocess.run([sys.executable, "-c", CHILD, str(ROOT / "benchmarks" / "memory.py"), str(tmp_path),
                          str(BUCKET_POINTS)],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    m = json.loads(res.stdout.strip().splitlines()[-1])
    extra = m["large"]["bytes"] - m["small"]["bytes"]
    assert extra > 40e6
    grown = m["large"]["tune_cfd"] - m["small"]["tune_cfd"]
    assert grown < GROWTH_PER_FILE_BYTE * extra, (grown / 1e6, extra / 1e6, m)
    # ingest holds one bucket of points and one batch of pulses whatever the file size
    assert m["large"]["ingest"] < INGEST_GROWTH_BYTES, m


def test_compressed_waveforms_give_one_error_saying_what_to_do(tmp_path, capsys):
    las = tmp_path / "flight.las"
    shutil.copy(RIEGL, las)
    shutil.copy(RIEGL.with_suffix(".wdp"), las.with_suffix(".wdz"))  # as LAStools names them
    with pytest.raises(SystemExit) as exc:
        main(["ingest", str(las), "--out", str(tmp_path / "p.parquet"), "--no-progress"])
    assert exc.value.code == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith("waveforest: error:")
    assert str(las) in err[0] and "flight.wdz" in err[0] and "laszip -i flight.las" in err[0]
    assert not (tmp_path / "p.parquet").exists()
