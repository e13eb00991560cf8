"""The warning path through the CLI, on a real file that warns (it stores no AGC)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
from click.testing import CliRunner

from waveforest.cli import cli

RIEGL = Path(__file__).parent / "data" / "real" / "riegl_fwf.las"


def test_ingest_warning_is_one_line_on_stderr(tmp_path):
    out = tmp_path / "pulses.parquet"
    res = CliRunner().invoke(cli, ["ingest", str(RIEGL), "--out", str(out), "--nominal-range", "600",
                                   "--no-progress"])
    assert res.exit_code == 0, res.output
    warned = [line for line in res.stderr.splitlines() if line.startswith("waveforest: warning:")]
    assert len(warned) == 1 and "no AGC" in warned[0] and str(RIEGL.name) in warned[0]
    assert pq.read_metadata(out).num_rows == 2368  # pulses = distinct GPS times (data README)


def test_ingest_warns_in_a_real_process(tmp_path):
    """As a user runs it: a separate interpreter with the default warning filters."""
    out = tmp_path / "pulses.parquet"
    proc = subprocess.run([sys.executable, "-m", "waveforest.cli", "ingest", str(RIEGL), "--out", str(out),
                           "--nominal-range", "600", "--no-progress"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "waveforest: warning:" in proc.stderr and out.exists()
