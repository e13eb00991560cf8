"""Unreadable files end with one clear message naming the file, exit code 1, and no output.

Each case runs ``waveforest ingest`` through the CLI entry point and checks the message,
the exit code, that no Parquet (nor any temporary file) is left, and that a previous
output of the same name survives.
"""

import os

import laspy
import numpy as np
import pytest
from fixtures.pulses import synthetic_pulses
from reference_io import patch, point_field_position, reference_header, vlr_body_position

from waveforest.cli import main
from waveforest.io.las.write import write_waveform_las


@pytest.fixture(scope="module")
def table():
    return synthetic_pulses(60, seed=31, n_samples=(64, 128))


def _write(tmp_path, table, name="f.las", **kw):
    return write_waveform_las(tmp_path / "in" / name, table, **kw)


def _ingest_fails(tmp_path, las, capsys, *extra, named=None, code=1):
    out_dir = tmp_path / "out"
    out_dir.mkdir(exist_ok=True)
    out = out_dir / "pulses.parquet"
    out.write_bytes(b"previous output")
    with pytest.raises(SystemExit) as exc:
        main(["ingest", str(las), "--out", str(out), "--no-progress", *extra])
    assert exc.value.code == code
    err = capsys.readouterr().err
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("waveforest: error:")]
    assert len(lines) == 1, err
    named = named or las
    assert str(named) in lines[0]
    assert out.read_bytes() == b"previous output"  # not lost, not half-overwritten
    assert sorted(os.listdir(out_dir)) == ["pulses.parquet"]  # no temporary file or spill left
    _ingest_fails.stderr = err
    return lines[0]


def test_non_waveform_point_format(tmp_path, capsys):
    las = laspy.create(point_format=1, file_version="1.2")
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    path = tmp_path / "plain.las"
    las.write(path)
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "LAS 1.2 has no waveform packets" in msg
    las = laspy.create(point_format=6, file_version="1.4")
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.arange(5.0)
    path = tmp_path / "plain14.las"
    las.write(path)
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "point format 6 carries no waveform packets" in msg


def test_not_a_las_file(tmp_path, capsys):
    path = tmp_path / "junk.las"
    path.write_bytes(b"this is not LAS at all" * 20)
    assert "not a LAS file" in _ingest_fails(tmp_path, path, capsys)


def test_missing_file(tmp_path, capsys):
    """A missing input file is a usage error (exit 2) naming the argument and the path."""
    err = _ingest_fails(tmp_path, tmp_path / "nope.las", capsys, code=2)
    assert "does not exist" in err and "nope.las" in err


@pytest.mark.parametrize("storage", ["internal", "external"])
def test_truncated_point_records(tmp_path, capsys, table, storage):
    path = _write(tmp_path, table, storage=storage)
    h = reference_header(path)
    cut = h["offset_to_points"] + h["record_length"] * (h["n_points"] // 2) + 7
    with open(path, "r+b") as fh:
        fh.truncate(cut)
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "truncated file" in msg and f"{h['n_points']} points" in msg


def test_truncated_internal_waveform_data(tmp_path, capsys, table):
    path = _write(tmp_path, table, storage="internal")
    with open(path, "r+b") as fh:
        fh.truncate(path.stat().st_size - 100)
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "beyond the end of the waveform record" in msg and "truncated" in msg


def test_missing_wdp(tmp_path, capsys, table):
    path = _write(tmp_path, table, storage="external")
    path.with_suffix(".wdp").unlink()
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "f.wdp is missing" in msg and "external" in msg


def test_short_wdp(tmp_path, capsys, table):
    path = _write(tmp_path, table, storage="external")
    wdp = path.with_suffix(".wdp")
    with open(wdp, "r+b") as fh:
        fh.truncate(wdp.stat().st_size // 2)
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "f.wdp" in msg and "short" in msg
    assert "waveforest: warning:" in _ingest_fails.stderr and "cut short" in _ingest_fails.stderr  # header too


def test_descriptor_index_out_of_range(tmp_path, capsys, table):
    path = _write(tmp_path, table)
    patch(path, point_field_position(path, 3, "wpi"), "<B", 9)
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "point 3 uses wave packet descriptor index 9" in msg and "out of range" in msg


def test_descriptor_with_zero_samples_in_use(tmp_path, capsys, table):
    path = _write(tmp_path, table)
    patch(path, vlr_body_position(path, 100) + 2, "<I", 0)  # descriptor 1: 0 samples
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "describes no waveform" in msg


def test_unsupported_compression(tmp_path, capsys, table):
    path = _write(tmp_path, table)
    patch(path, vlr_body_position(path, 101) + 1, "<B", 1)  # descriptor 2: compression 1
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "compression type 1" in msg and "descriptor 2" in msg


def test_packet_beyond_end_of_waveform_data(tmp_path, capsys, table):
    path = _write(tmp_path, table, storage="external")
    patch(path, point_field_position(path, 5, "off"), "<Q", 10**9)
    msg = _ingest_fails(tmp_path, path, capsys)
    assert "point 5" in msg and "byte offset 1000000000" in msg


def test_laz_compressed(tmp_path, capsys, table):
    path = _write(tmp_path, table)
    patch(path, 104, "<B", 9 | 0x80)  # the LAZ flag in the point format byte
    assert "LAZ-compressed" in _ingest_fails(tmp_path, path, capsys)


def test_bad_trajectory_is_an_error(tmp_path, capsys, table):
    path = _write(tmp_path, table)
    traj = tmp_path / "traj.csv"
    gps = table["gps_time"].to_numpy()
    traj.write_text("gps_time,x,y,z\n" + "\n".join(f"{float(t)!r},0,0,1000" for t in (gps[0], gps[10])))
    msg = _ingest_fails(tmp_path, path, capsys, "--trajectory", str(traj), named=traj)
    assert "49 pulse(s) lie outside the trajectory" in msg


def test_failure_after_spilling_leaves_nothing(tmp_path, capsys):
    """A large file (bucketed, spilled beside the output) failing mid-way leaves no spill."""
    t = synthetic_pulses(3000, seed=32)
    path = _write(tmp_path, t)
    traj = tmp_path / "traj.csv"
    gps = t["gps_time"].to_numpy()
    traj.write_text("gps_time,x,y,z\n" + "\n".join(f"{float(g)!r},0,0,1000" for g in (gps[0], gps[2000])))
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("ingest:\n  bucket_points: 1000\n  batch_pulses: 500\n")
    msg = _ingest_fails(tmp_path, path, capsys, "--trajectory", str(traj), "--config", str(cfg), named=traj)
    assert "pulse(s) lie outside the trajectory" in msg


def test_info_reports_errors_too(tmp_path, capsys, table):
    path = _write(tmp_path, table, storage="external")
    path.with_suffix(".wdp").unlink()
    with pytest.raises(SystemExit) as exc:
        main(["info", str(path)])
    assert exc.value.code == 1
    assert "f.wdp is missing" in capsys.readouterr().err
