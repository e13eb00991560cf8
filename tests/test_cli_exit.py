"""The console entry point (``waveforest.cli:entry``) ends as a normal exit would: main's exit
code, every line printed, the atexit handlers run, the output file complete."""

from __future__ import annotations

import subprocess
import sys

import pyarrow.parquet as pq

ENTRY = """
import atexit, sys
atexit.register(lambda: print("atexit ran", flush=True))
from waveforest.cli import entry
sys.argv = ["waveforest"] + sys.argv[1:]
entry()
"""


def _run(*args):
    return subprocess.run([sys.executable, "-c", ENTRY, *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def test_success_prints_everything_runs_atexit_and_writes_the_file(tmp_path):
    out = tmp_path / "sigma.parquet"
    r = _run("trace", "--species", "sand_road", "--height", "0.1", "--rays", "500", "--out", out)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith(f"wrote {out}") and r.stdout.rstrip().endswith("atexit ran")
    assert pq.read_table(out).num_rows > 0


def test_errors_keep_their_exit_codes():
    bad = _run("trace", "no_such.ply", "--out", "x.parquet")
    assert bad.returncode == 1 and bad.stderr.count("waveforest: error:") == 1
    assert "atexit ran" in bad.stdout
    assert _run("no-such-command").returncode == 2  # click's usage error
    assert _run("--version").returncode == 0
