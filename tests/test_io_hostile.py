"""Hostile LAS input and output paths: each gets one clear answer, and nothing is left behind.

Inputs are copies of the real RIEGL file (tests/data/real/README.md: LAS 1.4, format 9,
external waveforms, 2,535 points of 63 bytes from byte 10,071) with one field broken.
Commands run through ``waveforest.cli.main``: in-process where only the message and the
exit code matter, in a subprocess where a hang or a signal is what is tested.
"""

import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import time

import numpy as np
import pyarrow.parquet as pq
import pytest
from fixtures.cli import run_cli
from fixtures.pulses import synthetic_pulses
from reference_io import RIEGL, patch, point_field_position, reference_points, vlr_body_position
from test_io_las_roundtrip import assert_tables_equal

from waveforest.atomic import atomic_path
from waveforest.errors import WaveforestError
from waveforest.io.las.format import LasWaveformWarning
from waveforest.io.las.read import read_waveform_las
from waveforest.io.las.write import write_waveform_las

PREVIOUS = b"previous output"
HANG_TIMEOUT_S = 120
"""A command on the 170 kB RIEGL file takes about a second; a hang takes forever."""
MEMORY_LIMIT = 1 << 31
"""Address space of a subprocess here: a runaway allocation fails instead of swapping."""


@pytest.fixture
def riegl(tmp_path):
    """A private copy of the RIEGL file and its .wdp."""
    folder = tmp_path / "in"
    folder.mkdir()
    las = folder / "riegl.las"
    shutil.copy(RIEGL, las)
    shutil.copy(RIEGL.with_suffix(".wdp"), las.with_suffix(".wdp"))
    return las


def _run(args, capsys):
    """``main(args)``: (exit code, stdout, stderr)."""
    return run_cli(args, capsys)


def _fails(tmp_path, las, capsys, command="ingest"):
    """Run ``command`` on ``las``: exit 1, one error line naming the file, no output left."""
    out = tmp_path / "out" / "pulses.parquet"
    out.parent.mkdir(exist_ok=True)
    out.write_bytes(PREVIOUS)
    extra = ["--out", out, "--no-progress"] if command == "ingest" else []
    code, _, err = _run([command, las, *extra], capsys)
    assert code == 1, err
    lines = [ln for ln in err.splitlines() if ln.startswith("waveforest: error:")]
    assert len(lines) == 1 and str(las) in lines[0], err
    assert "Traceback" not in err
    assert sorted(os.listdir(out.parent)) == ["pulses.parquet"] and out.read_bytes() == PREVIOUS
    return lines[0]


def _subprocess(args, **kw):
    """``python -m waveforest.cli args`` under a memory limit; a hang fails the test."""

    def limit():
        import resource

        resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))

    return subprocess.run(
        [sys.executable, "-m", "waveforest.cli", *map(str, args)],
        capture_output=True, text=True, timeout=HANG_TIMEOUT_S, preexec_fn=limit, **kw,
    )


# -- 1. counts bounded by the header geometry ---------------------------------------------


@pytest.mark.parametrize("command", ["info", "ingest"])
def test_corrupt_vlr_count_is_an_error_not_a_hang(riegl, tmp_path, command):
    patch(riegl, 100, "<I", 0xFFFFFFFF)  # number of VLRs
    out = tmp_path / "out.parquet"
    r = _subprocess([command, riegl] + (["--out", out, "--no-progress"] if command == "ingest" else []))
    assert r.returncode == 1, r.stderr
    assert r.stderr.count("waveforest: error:") == 1 and "Traceback" not in r.stderr
    assert str(riegl) in r.stderr and "number of VLRs is 4294967295" in r.stderr
    assert "at most 179 VLR headers (54 bytes each)" in r.stderr  # (10071 - 375) // 54
    assert not out.exists()


def test_vlr_running_past_the_point_data(riegl, tmp_path, capsys):
    patch(riegl, 375 + 20, "<H", 65535)  # record length of the first VLR
    msg = _fails(tmp_path, riegl, capsys, "info")
    assert "VLR 1 of 105" in msg and "65535 bytes" in msg and "point data (byte 10071)" in msg


@pytest.mark.parametrize("command", ["info", "ingest"])
def test_corrupt_evlr_count_and_start(riegl, tmp_path, capsys, command):
    size = riegl.stat().st_size
    with open(riegl, "ab") as fh:  # room for two EVLR headers after the points
        fh.write(b"\0" * 120)
    patch(riegl, 235, "<QI", size, 0xFFFFFFFF)  # start of first EVLR, number of EVLRs
    msg = _fails(tmp_path, riegl, capsys, command)
    assert "number of EVLRs is 4294967295" in msg and "at most 2 EVLR headers" in msg
    patch(riegl, 235, "<QI", 10**15, 1)  # an EVLR start beyond the end of the file
    msg = _fails(tmp_path, riegl, capsys, command)
    assert "start of the first EVLR is byte 1000000000000000" in msg


# -- 2. silent garbage --------------------------------------------------------------------


@pytest.mark.parametrize("command", ["info", "ingest"])
def test_point_count_zero_on_a_file_with_points(riegl, tmp_path, capsys, command):
    patch(riegl, 247, "<Q", 0)  # 64-bit count (the legacy count is 0 already: format 9)
    msg = _fails(tmp_path, riegl, capsys, command)
    assert "legacy and 64-bit point counts are 0" in msg and "hold 2535 point records of 63 bytes" in msg


def test_point_count_zero_las13(tmp_path, capsys):
    las = write_waveform_las(tmp_path / "in" / "f13.las", synthetic_pulses(40, seed=3), version="1.3", point_format=4)
    patch(las, 107, "<I", 0)
    msg = _fails(tmp_path, las, capsys)
    assert "point count is 0" in msg and "the waveform data record" in msg


def _ingest(las, tmp_path, capsys):
    out = tmp_path / "out" / "pulses.parquet"
    code, stdout, err = _run(["ingest", las, "--out", out, "--no-progress"], capsys)
    assert code == 0, err
    return pq.read_table(out), stdout, err


def test_nan_gps_times_are_dropped_and_counted(riegl, tmp_path, capsys):
    pts = reference_points(RIEGL)
    bad = [5, 600, 2000]
    for i in bad:
        patch(riegl, point_field_position(riegl, i, "gps"), "<d", float("nan"))
    table, stdout, err = _ingest(riegl, tmp_path, capsys)
    assert "3 points with a non-finite GPS time dropped" in stdout  # the summary line
    assert "waveforest: warning:" in err and "3 point(s) with a non-finite GPS time dropped" in err
    kept = {p["gps"] for i, p in enumerate(pts) if i not in bad}
    assert table.num_rows == len(kept)  # every pulse of the other points, none of NaN time
    assert set(table["gps_time"].to_pylist()) == kept


@pytest.mark.parametrize("field", ["direction", "location"])
def test_unusable_beam_geometry_drops_the_packet(riegl, tmp_path, capsys, field):
    pts = reference_points(RIEGL)
    single = [p for p in pts if p["nret"] == 1 and p["wpi"] > 0][:2]  # pulses of one return
    for p in single:
        if field == "direction":
            patch(riegl, point_field_position(riegl, p["index"], "xt"), "<3f", 0.0, 0.0, 0.0)
        else:
            patch(riegl, point_field_position(riegl, p["index"], "loc"), "<f", float("nan"))
    table, stdout, err = _ingest(riegl, tmp_path, capsys)
    assert "2 points with an unusable beam geometry kept without their packet" in stdout
    assert "2 pulses without waveform skipped" in stdout
    assert "2 point(s) with an unusable beam geometry" in err
    assert table.num_rows == 2368 - 2 and not ({p["gps"] for p in single} & set(table["gps_time"].to_pylist()))
    for col in ("dir_x", "dir_y", "dir_z", "anchor_x", "anchor_y", "anchor_z"):
        assert np.all(np.isfinite(table[col].to_numpy())), col
    assert np.all(np.isfinite(table["echo_time_ns"].combine_chunks().flatten().to_numpy()))


def test_eight_bit_descriptor_on_sixteen_bit_packets(riegl, tmp_path, capsys):
    patch(riegl, vlr_body_position(riegl, 100), "<B", 8)  # descriptor 1: 8 bits per sample
    msg = _fails(tmp_path, riegl, capsys)
    assert "descriptor 1 says 8 bits per sample (60 samples = 60 bytes)" in msg
    assert "packet size is 120 bytes, i.e. 16-bit samples" in msg


def test_non_finite_digitizer_gain(riegl, tmp_path, capsys):
    patch(riegl, vlr_body_position(riegl, 101) + 10, "<d", float("nan"))  # descriptor 2 gain
    assert "descriptor 2 has digitizer gain nan" in _fails(tmp_path, riegl, capsys)


@pytest.mark.parametrize("pos, value, field", [(131, float("nan"), "scale factors"), (163, float("inf"), "offsets")])
def test_non_finite_scale_or_offset(riegl, tmp_path, capsys, pos, value, field):
    patch(riegl, pos, "<d", value)
    assert f"header {field}" in _fails(tmp_path, riegl, capsys)


# -- 3. text fields that are not UTF-8 ----------------------------------------------------


def test_non_utf8_text_fields_read_on_with_a_warning(riegl, tmp_path, capsys):
    clean = read_waveform_las(RIEGL, dataset="x", agc_attribute="Amplitude")
    patch(riegl, 637 + 22, "<B", 0xE9)  # description of VLR 2 (WPD#1, in use)
    patch(riegl, 797 + 2 + 3, "<B", 0xE9)  # user id of VLR 4 (WPD#3, unused)
    patch(riegl, 9633 + 54 + 160, "<B", 0xFF)  # description of extra-bytes descriptor 1 ("Amplitude")
    expected = "non-UTF-8 bytes in VLR 2 description, VLR 4 user id, extra-bytes descriptor 1 description"
    with pytest.warns(LasWaveformWarning, match=expected):
        back = read_waveform_las(riegl, dataset="x", agc_attribute="Amplitude", chunk_points=500)
    assert_tables_equal(back, clean)  # points and the AGC extra bytes read through the patched header
    assert np.nanmax(back["agc"].to_numpy()) > 0
    code, out, err = _run(["info", riegl], capsys)
    assert code == 0 and expected in out and "extra bytes: Amplitude, Pulse width" in out


def test_non_utf8_extra_bytes_name_keeps_the_points(riegl, tmp_path, capsys):
    patch(riegl, 9633 + 54 + 192 + 4, "<B", 0xCB)  # name of extra-bytes descriptor 2 ("Pulse width")
    table, stdout, err = _ingest(riegl, tmp_path, capsys)
    assert "extra-bytes descriptor 2 name replaced by '?'" in err
    clean = read_waveform_las(RIEGL, agc_attribute=None)
    assert_tables_equal(table.drop_columns(["dataset"]), clean.drop_columns(["dataset"]))


# -- 4. output paths ----------------------------------------------------------------------


def _specials(tmp_path):
    """Non-regular files to give as ``--out``: a FIFO, a socket, a directory and, as root,
    look-alikes of /dev/null and /dev/full (made here: the real ones must not be at stake)."""
    found = {}
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    found["FIFO"] = fifo
    sock = socket.socket(socket.AF_UNIX)
    sock.bind(str(tmp_path / "sock"))
    sock.close()
    found["socket"] = tmp_path / "sock"
    (tmp_path / "dir.parquet").mkdir()
    found["directory"] = tmp_path / "dir.parquet"
    if os.geteuid() == 0:
        for name, minor in (("null", 3), ("full", 7)):
            os.mknod(tmp_path / name, stat.S_IFCHR | 0o666, os.makedev(1, minor))
            found["character device"] = found.get("character device", []) + [tmp_path / name]
    return found


def test_atomic_path_refuses_non_regular_files(tmp_path):
    for kind, paths in _specials(tmp_path).items():
        for path in paths if isinstance(paths, list) else [paths]:
            mode = os.stat(path).st_mode
            with pytest.raises(WaveforestError, match=f"{path}: the output exists and is a"):
                with atomic_path(path) as tmp:
                    tmp.write_bytes(b"x")
            assert os.stat(path).st_mode == mode, kind  # untouched
            assert not [n for n in os.listdir(tmp_path) if n.endswith(".part")]


def test_ingest_refuses_a_device_or_fifo(riegl, tmp_path, capsys):
    specials = _specials(tmp_path)
    targets = [specials["FIFO"], specials["socket"]] + specials.get("character device", [])
    for target in targets:
        mode = os.stat(target).st_mode
        code, _, err = _run(["ingest", riegl, "--out", target, "--no-progress"], capsys)
        assert code == 1 and err.count("waveforest: error:") == 1, err
        assert f"{target}: the output exists and is a" in err and "refusing to replace it" in err
        assert os.stat(target).st_mode == mode


def test_las_writer_refuses_a_fifo(tmp_path):
    os.mkfifo(tmp_path / "f.las")
    with pytest.raises(WaveforestError, match="is a FIFO"):
        write_waveform_las(tmp_path / "f.las", synthetic_pulses(3))
    os.mkfifo(tmp_path / "g.wdp")
    with pytest.raises(WaveforestError, match="g.wdp: the output exists and is a FIFO"):
        write_waveform_las(tmp_path / "g.las", synthetic_pulses(3), storage="external")
    assert sorted(os.listdir(tmp_path)) == ["f.las", "g.wdp"]


def test_missing_output_folder_is_made_and_a_file_in_the_way_is_an_error(riegl, tmp_path, capsys):
    deep = tmp_path / "a" / "b" / "pulses.parquet"
    code, _, err = _run(["ingest", riegl, "--out", deep, "--no-progress"], capsys)
    assert code == 0 and deep.is_file(), err
    (tmp_path / "plain").write_text("a file")
    code, _, err = _run(["ingest", riegl, "--out", tmp_path / "plain" / "x.parquet", "--no-progress"], capsys)
    assert code == 1 and err.count("waveforest: error:") == 1 and "Traceback" not in err
    assert f"{tmp_path / 'plain' / 'x.parquet'}: cannot create the output folder {tmp_path / 'plain'}" in err


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_unwritable_output_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(WaveforestError, match=f"{ro / 'x.parquet'}: cannot create a file in {ro}"):
            with atomic_path(ro / "x.parquet"):
                pass
    finally:
        ro.chmod(0o700)


def test_write_error_inside_atomic_path_names_the_output(tmp_path):
    out = tmp_path / "x.bin"
    out.write_bytes(PREVIOUS)
    with pytest.raises(WaveforestError, match=f"{out}: cannot write the output"):
        with atomic_path(out) as tmp:
            raise OSError(28, "No space left on device", str(tmp))
    assert out.read_bytes() == PREVIOUS and os.listdir(tmp_path) == ["x.bin"]


# -- 5. SIGTERM ---------------------------------------------------------------------------

_SLOW_INGEST = """
import sys, time
import waveforest.io.pulses as tables
check = tables.check_pulses
def slow(*args, **kw):  # a slow disk: every batch takes a while to write
    time.sleep(0.2)
    return check(*args, **kw)
tables.check_pulses = slow
from waveforest.cli import main
main(sys.argv[1:])
"""


def test_sigterm_removes_partial_outputs(riegl, tmp_path):
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    out = out_dir / "pulses.parquet"
    out.write_bytes(PREVIOUS)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("ingest:\n  bucket_points: 1000\n  batch_pulses: 50\n")  # 2 passes, spilled buckets
    proc = subprocess.Popen(
        [sys.executable, "-c", _SLOW_INGEST, "ingest", str(riegl), "--out", str(out), "--no-progress", "--config", str(cfg)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + HANG_TIMEOUT_S
        while not any(n.endswith(".part") for n in os.listdir(out_dir)):
            assert proc.poll() is None and time.monotonic() < deadline, "ingest ended before writing"
            time.sleep(0.02)
        time.sleep(0.3)  # a few batches into the .part file
        assert any(n.startswith(".waveforest-ingest-") for n in os.listdir(out_dir))  # the spill, too
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=HANG_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 143, err
    assert "terminated by signal SIGTERM" in err and "Traceback" not in err
    assert os.listdir(out_dir) == ["pulses.parquet"] and out.read_bytes() == PREVIOUS
