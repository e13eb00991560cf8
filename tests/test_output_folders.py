"""Output folders: a folder holding files the command did not write is refused (exit 2) unless
--force; a re-run over the command's own output needs no --force; a failed or interrupted
command leaves no partial output and the earlier output as it was (waveforest.atomic.OutputFolder)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fixtures.real import quicklook_of_riegl
from fixtures.tables import plate_scene

from waveforest import config
from waveforest.atomic import MANIFEST, FolderNotOursError, OutputFolder, atomic_path, output_files
from waveforest.cli import main
from waveforest.errors import WaveforestError
from waveforest.stages import sensitivity, sensor_study

RIEGL = Path(__file__).parent / "data" / "real" / "riegl_fwf.las"
TIMEOUT_S = 300


def wf(*args) -> int:
    """Run ``waveforest ARGS`` in process; its exit status."""
    try:
        main([str(a) for a in args])
    except SystemExit as exc:
        return exc.code
    return 0


def snapshot(folder: Path) -> dict:
    """Relative path -> bytes of every file under ``folder``."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def temporaries(parent: Path) -> list[str]:
    return [n for n in os.listdir(parent) if n.endswith((".part", ".old"))]


def _commands(tmp: Path) -> dict:
    """Each folder-writing command: (arguments before --out, arguments that fail after the folder check)."""
    junk = tmp / "junk.parquet"
    junk.write_text("not a table\n")
    las = tmp / "junk.las"
    las.write_text("a text file, not LAS\n")
    bad_cfg = tmp / "bad_datasets.yaml"
    bad_cfg.write_text("datasets: ['2010_12_1', '2011_99_1']\n")
    return {
        "synthesize": (["synthesize", "--quiet"], ["--config", bad_cfg]),
        "quicklook": (["quicklook", las, "--no-progress"], []),
        "compare": (["compare", "--real", junk, "--sim", junk], []),
        "sensitivity": (["sensitivity"], ["--system", junk]),
        "sensor-study": (["sensor-study"], ["--system", junk]),
        "diagnose": (["diagnose", "--selected", junk, "--features-real", junk, "--calibration", junk,
                      "--datasets", junk], []),
    }


@pytest.mark.parametrize("command", ["synthesize", "quicklook", "compare", "sensitivity", "sensor-study", "diagnose"])
def test_a_folder_with_a_foreign_file_is_refused_unless_force(command, tmp_path, capsys):
    head, failing = _commands(tmp_path)[command]
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert wf(*head, "--out", out, *failing) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"waveforest: error: {out}/: holds notes.txt, which {command} did not write; use --force to replace it"
    assert (out / "notes.txt").read_text() == "mine"
    # --force passes the check; the run then fails on its input (exit 1) and the folder is kept
    assert wf(*head, "--out", out, "--force", *failing) == 1
    err = capsys.readouterr().err
    assert err.count("waveforest: error:") == 1 and "did not write" not in err
    assert snapshot(out) == {"notes.txt": b"mine"} and temporaries(tmp_path) == []


@pytest.mark.parametrize("command", ["quicklook", "compare", "diagnose"])
def test_a_failing_run_leaves_no_folder(command, tmp_path, capsys):
    head, failing = _commands(tmp_path)[command]
    out = tmp_path / "new" / "out"
    assert wf(*head, "--out", out, *failing) == 1
    assert "Traceback" not in capsys.readouterr().err
    assert not (tmp_path / "new").exists() and temporaries(tmp_path) == []


def _features(path: Path, source: str, rng) -> Path:
    n = 12
    pd.DataFrame(dict(dataset="2010_12_1", pulse_id=np.arange(n), source=source, species="raspberry",
                      sample_id="raspberry-1", H=rng.normal(0.6, 0.1, n), Apeak=rng.normal(108, 9, n),
                      E=rng.normal(1300, 100, n), FWHM=rng.normal(9, 1, n), Npeaks=np.ones(n),
                      n_echoes=1)).to_parquet(path)
    return path


def test_compare_reruns_over_its_own_output_and_force_replaces_a_foreign_one(tmp_path, capsys):
    rng = np.random.default_rng(0)
    real, sim = _features(tmp_path / "r.parquet", "real", rng), _features(tmp_path / "s.parquet", "sim", rng)
    out = tmp_path / "cmp"
    args = ["compare", "--real", real, "--sim", sim, "--out", out]
    assert wf(*args) == 0
    first = snapshot(out)
    assert {"table3.csv", "table3.md", "order_check.csv", MANIFEST} <= set(first)
    manifest = json.loads(first[MANIFEST])
    assert manifest["command"] == "compare" and set(manifest["files"]) == set(first) - {MANIFEST}
    assert wf(*args) == 0  # its own earlier output: no --force needed, the same bytes
    assert snapshot(out) == first
    (out / "notes.txt").write_text("mine")
    assert wf(*args) == 2 and (out / "notes.txt").exists()
    assert wf(*args, "--force") == 0
    assert snapshot(out) == first and temporaries(tmp_path) == []
    # a failing run keeps the earlier output as it was
    junk = tmp_path / "junk.parquet"
    junk.write_text("not a table\n")
    assert wf("compare", "--real", real, "--sim", junk, "--out", out) == 1
    assert snapshot(out) == first and temporaries(tmp_path) == []
    capsys.readouterr()


def _studies_cfg():
    return config.load(overrides={
        "seed": 11, "mcrt": {"n_rays": 50, "max_order": 2},
        "sensitivity": {"pulses": 4, "instances": 2, "mean_leaf_angle_deg": [], "leaf_tau": [], "leaf_rho": [0.3],
                        "leaf_area_scale": []},
        "sensor_study": {"pulses": 6, "instances": 2, "divergences_mrad": [0.15], "pulse_widths_ns": [7.2],
                         "samplings_ns": [1.0], "cv_folds": 2, "max_scan_zenith_deg": 5.0}})


@pytest.mark.parametrize("stage, command", [(sensitivity, "sensitivity"), (sensor_study, "sensor-study")])
def test_studies_rerun_over_their_own_output_and_refuse_a_foreign_one(stage, command, tmp_path):
    cfg = _studies_cfg()
    out = tmp_path / "study"
    r = stage.run(out, cfg, progress=False, scene_builder=plate_scene)
    assert r.table.parent == out and r.table.exists() and r.figure.exists()
    first = snapshot(out)
    assert json.loads(first[MANIFEST])["command"] == command
    stage.run(out, cfg, progress=False, scene_builder=plate_scene)
    assert snapshot(out).keys() == first.keys()
    (out / "sub").mkdir()
    (out / "sub" / "data.csv").write_text("x\n")
    with pytest.raises(FolderNotOursError, match=r"holds sub/, which .* did not write"):
        stage.run(out, cfg, progress=False, scene_builder=plate_scene)
    stage.run(out, cfg, progress=False, scene_builder=plate_scene, force=True)
    assert not (out / "sub").exists() and snapshot(out).keys() == first.keys() and temporaries(tmp_path) == []


def test_output_folder_rules(tmp_path):
    """The manifest names the command: another command's output is refused, naming the writer;
    an entry the manifest does not list is refused; a file is not a folder; failure keeps all."""
    out = tmp_path / "o"
    with OutputFolder(out, "compare") as tmp:
        (tmp / "a.csv").write_text("1\n")
    assert snapshot(out).keys() == {"a.csv", MANIFEST}
    with pytest.raises(FolderNotOursError, match=r"holds a\.csv, which diagnose did not write \(compare did\)"):
        OutputFolder(out, "diagnose")
    OutputFolder(out, "compare")  # its own: accepted
    with pytest.raises(RuntimeError), OutputFolder(out, "compare") as tmp:
        (tmp / "b.csv").write_text("2\n")
        raise RuntimeError("boom")
    assert snapshot(out).keys() == {"a.csv", MANIFEST} and temporaries(tmp_path) == []
    (out / MANIFEST).write_text("not json")  # an unreadable manifest vouches for nothing
    with pytest.raises(FolderNotOursError, match=r"holds a\.csv \(and 1 more\)"):
        OutputFolder(out, "compare")
    (tmp_path / "f").write_text("x")
    with pytest.raises(WaveforestError, match="exists and is not a folder"):
        OutputFolder(tmp_path / "f", "compare", force=True)
    # a folder written while the command ran is found before the swap
    folder = OutputFolder(tmp_path / "late", "compare")
    with pytest.raises(FolderNotOursError), folder as tmp:
        (tmp / "a.csv").write_text("1\n")
        (tmp_path / "late").mkdir()
        (tmp_path / "late" / "x.txt").write_text("user")
    assert snapshot(tmp_path / "late") == {"x.txt": b"user"} and temporaries(tmp_path) == []


def test_a_folder_holding_an_input_or_not_writable_is_refused_even_with_force(tmp_path, monkeypatch):
    out = tmp_path / "o"
    (out / "data").mkdir(parents=True)
    (out / "data" / "in.las").write_text("input")
    with pytest.raises(WaveforestError, match=r"holds the input data/in\.las, which replacing the folder would delete"):
        OutputFolder(out, "quicklook", force=True, inputs=[out / "data" / "in.las"])
    OutputFolder(out, "quicklook", force=True, inputs=[tmp_path / "elsewhere.las"])  # not inside: accepted
    real = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if Path(p) == out else real(p, mode))
    with pytest.raises(WaveforestError, match="cannot write in the output folder"):
        OutputFolder(out, "quicklook", force=True)
    assert (out / "data" / "in.las").read_text() == "input"


def test_quicklook_force_never_deletes_its_input(looked, capsys):
    tmp, _, _ = looked
    assert wf("quicklook", tmp / RIEGL.name, "--out", tmp, "--no-progress", "--force") == 1
    assert "holds the input" in capsys.readouterr().err and (tmp / RIEGL.name).exists()


def test_output_files_publishes_all_or_none(tmp_path):
    a, b = tmp_path / "a.txt", tmp_path / "b.txt"
    a.write_text("old")
    with pytest.raises(RuntimeError), output_files():
        with atomic_path(a) as tmp:
            tmp.write_text("new")
        raise RuntimeError("boom")
    assert a.read_text() == "old" and sorted(os.listdir(tmp_path)) == ["a.txt"]
    with output_files():
        with atomic_path(a) as tmp:
            tmp.write_text("new")
        assert a.read_text() == "old"  # not yet
        with atomic_path(b) as tmp:
            tmp.write_text("b")
    assert a.read_text() == "new" and b.read_text() == "b" and sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt"]


@pytest.fixture(scope="module")
def looked(tmp_path_factory):
    """quicklook of the bundled RIEGL file: (folder with the input, output folder, its files)."""
    tmp = tmp_path_factory.mktemp("ql")
    _, out = quicklook_of_riegl(tmp)
    return tmp, out, snapshot(out)


def test_quicklook_reruns_over_its_own_output_and_force_replaces(looked, capsys):
    tmp, out, first = looked
    assert json.loads(first[MANIFEST])["files"] == sorted(set(first) - {MANIFEST})
    assert json.loads(first["cfd.json"])["source"] == str(out / "pulses.parquet")  # not the temporary folder
    (out / "notes.txt").write_text("mine")
    assert wf("quicklook", tmp / RIEGL.name, "--out", out, "--no-progress") == 2
    assert (out / "notes.txt").read_text() == "mine"
    assert wf("quicklook", tmp / RIEGL.name, "--out", out, "--no-progress", "--force") == 0
    assert set(snapshot(out)) == set(first)
    assert wf("quicklook", tmp / RIEGL.name, "--out", out, "--no-progress") == 0  # its own output
    assert snapshot(out)["pulses.parquet"] == first["pulses.parquet"]
    err = capsys.readouterr().err
    assert ".part" not in err and temporaries(tmp) == []


def test_quicklook_on_a_text_file_keeps_the_earlier_output(looked, tmp_path, capsys):
    _, out, _ = looked
    earlier = tmp_path / "look"
    shutil.copytree(out, earlier)
    before = snapshot(earlier)
    fake = tmp_path / "fake.las"
    fake.write_text("hello\n")
    assert wf("quicklook", fake, "--out", earlier, "--no-progress") == 1
    assert "Traceback" not in capsys.readouterr().err
    assert snapshot(earlier) == before and temporaries(tmp_path) == []


_WATCHED = """\
import signal, sys
signal.signal(signal.SIGINT, signal.default_int_handler)  # as a terminal gives it, even if started in the background
from waveforest.cli import main
main(sys.argv[1:])
"""


@pytest.mark.parametrize("earlier", [False, True], ids=["fresh", "over-earlier-output"])
def test_sigint_during_quicklook_leaves_no_partial_output(looked, tmp_path, earlier):
    src, first_out, _ = looked
    out = tmp_path / "look"
    if earlier:
        shutil.copytree(first_out, out)
    before = snapshot(out) if earlier else None
    proc = subprocess.Popen([sys.executable, "-c", _WATCHED, "quicklook", str(src / RIEGL.name), "--out", str(out),
                             "--no-progress"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while not any(p.is_dir() and p.name.endswith(".part") and any(p.iterdir()) for p in tmp_path.iterdir()):
            assert proc.poll() is None and time.monotonic() < deadline, "quicklook ended before writing"
            time.sleep(0.02)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "interrupted; partial outputs removed" in err and "Traceback" not in err
    assert temporaries(tmp_path) == []
    if earlier:
        assert snapshot(out) == before
    else:
        assert not out.exists()
