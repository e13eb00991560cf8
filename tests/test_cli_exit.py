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


def test_errors_keep_their_exit_codes(tmp_path):
    junk = tmp_path / "junk.ply"
    junk.write_text("not a PLY file\n")
    bad = _run("trace", junk, "--out", tmp_path / "x.parquet")  # bad input content
    assert bad.returncode == 1 and bad.stderr.count("waveforest: error:") == 1, bad.stderr
    assert "atexit ran" in bad.stdout
    usage = _run("no-such-command")  # a usage error: one line
    assert usage.returncode == 2 and usage.stderr.strip().startswith("waveforest: error: No such command")
    assert len(usage.stderr.strip().splitlines()) == 1, usage.stderr
    assert _run("--version").returncode == 0
