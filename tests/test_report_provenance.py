"""report provenance: the code's commit, every input file's SHA-256 and the machine, in one table
of the opening section; Table 4's N is the accuracy's; the sensor study's rows go by value."""

from __future__ import annotations

import hashlib
import html
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from test_report_build import _results

from waveforest.report import provenance
from waveforest.report.build import table4
from waveforest.report.provenance import (
    GitState,
    checkout_root,
    code_text,
    git_state,
    head_from_files,
    input_files,
    provenance_table,
    sha256_files,
)
from waveforest.stages.report import run

HAS_GIT = shutil.which("git") is not None


def _section(md: str, title: str) -> str:
    parts = re.split(r"^## (.+)$", md, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2]))[title]


def _git(root: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(root), "-c", "user.name=t", "-c", "user.email=t@t",
                           "-c", "commit.gpgsign=false", *args], capture_output=True, text=True, check=True).stdout


@pytest.mark.skipif(not HAS_GIT, reason="git not installed")
def test_git_state_names_the_commit_and_the_uncommitted_changes(tmp_path):
    root = tmp_path / "checkout"
    root.mkdir()
    _git(root, "init", "-q", "-b", "main")
    (root / "a.py").write_text("x = 1\n")
    _git(root, "add", "a.py")
    _git(root, "commit", "-q", "-m", "one")
    commit = _git(root, "rev-parse", "HEAD").strip()
    (root / "new.py").write_text("")  # untracked: not a change of the committed code
    state = git_state(root)
    assert (state.commit, state.branch, state.dirty) == (commit, "main", 0)
    assert code_text(state).endswith(f"commit {commit} (branch main); no uncommitted changes in tracked files")
    (root / "a.py").write_text("x = 2\n")
    assert git_state(root).dirty == 1
    assert "uncommitted changes in 1 tracked file" in code_text(git_state(root))
    # without git: the same commit from the .git files, loose ref and packed, changes unknown
    by_files = git_state(root, use_git=False)
    assert (by_files.commit, by_files.branch, by_files.dirty) == (commit, "main", None)
    assert "uncommitted changes unknown (read from .git; git not found)" in code_text(by_files)
    _git(root, "pack-refs", "--all")
    assert not (root / ".git" / "refs" / "heads" / "main").exists()
    assert head_from_files(root) == (commit, "main")
    # a linked worktree: .git is a file pointing at its git dir, the refs in the common dir
    _git(root, "worktree", "add", "-q", "--detach", str(tmp_path / "wt"))
    assert head_from_files(tmp_path / "wt") == (commit, None)


def test_head_from_files_needs_no_git(tmp_path):
    git = tmp_path / ".git"
    (git / "refs" / "heads").mkdir(parents=True)
    (git / "HEAD").write_text("ref: refs/heads/dev\n")
    (git / "packed-refs").write_text("# pack-refs with: peeled\n" + "a" * 40 + " refs/heads/dev\n")
    assert head_from_files(tmp_path) == ("a" * 40, "dev")
    (git / "refs" / "heads" / "dev").write_text("b" * 40 + "\n")  # a loose ref wins over packed-refs
    assert head_from_files(tmp_path) == ("b" * 40, "dev")
    (git / "HEAD").write_text("c" * 40 + "\n")
    assert head_from_files(tmp_path) == ("c" * 40, None)


def test_not_a_checkout_is_said_not_failed(tmp_path):
    installed = tmp_path / "venv" / "lib" / "site-packages" / "waveforest"
    installed.mkdir(parents=True)
    (tmp_path / ".git").mkdir()  # a checkout above a venv does not make the installed copy one
    assert checkout_root(installed) is None
    assert checkout_root(tmp_path / "src" / "waveforest") == tmp_path
    state = git_state(tmp_path / "venv")
    assert state.root is None and "not a git checkout, no commit to name" in code_text(state)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / ".git").write_text("nonsense\n")  # unreadable: said in the cell, no exception
    assert "commit unknown" in code_text(git_state(broken, use_git=False))


def _campaign(tmp_path) -> Path:
    c = tmp_path / "campaign"
    c.mkdir()
    pd.DataFrame(dict(dataset=["d1", "d2"], year=[2010, 2012], las_file=["flight_1.las", "flight_2.las"],
                      trajectory_file=["t1.csv", "t2.csv"], mean_range_m=[1000.0, 1000.0],
                      pulse_width_fwhm_ns=[7.0, 7.0], footprint_diameter_m=[0.2, 0.2],
                      sampling_ns=[1.0, 1.0])).to_csv(c / "datasets.csv", index=False)
    rng = np.random.default_rng(3)
    for name in ("fields.csv", "flight_1.las", "flight_1.wdp", "t1.csv", "flight_2.las", "t2.csv"):
        (c / name).write_bytes(rng.bytes(int(rng.integers(10, 3000))))
    return c


def test_input_files_are_those_the_campaign_tables_name_with_their_sha256(tmp_path, monkeypatch, capsys):
    c = _campaign(tmp_path)
    files = input_files(c, ["d1", "d2"])
    assert [p.name for p in files] == ["datasets.csv", "fields.csv", "targets.csv", "flight_1.las", "flight_1.wdp",
                                       "t1.csv", "flight_2.las", "t2.csv"]
    monkeypatch.setattr(provenance, "CHUNK_BYTES", 7)  # many chunks per file: the same digest
    digests = sha256_files(files, progress=False)
    assert set(digests) == set(files) - {c / "targets.csv"}
    for p, h in digests.items():
        assert h == hashlib.sha256(p.read_bytes()).hexdigest()
    monkeypatch.setattr(provenance, "PROGRESS_DELAY_S", 0.0)  # hashing that takes long shows a bar
    sha256_files(files, progress=True)
    assert "report: SHA-256 of the inputs" in capsys.readouterr().err
    # a dataset datasets.csv does not name, or no datasets.csv: the virtual campaign's names
    (c / "datasets.csv").unlink()
    assert [p.name for p in input_files(c, ["2010_12_1"])][3:] == ["2010_12_1.las", "2010_12_1_trajectory.csv"]


def test_provenance_table_one_row_per_item_and_the_missing_said(tmp_path, capsys):
    c = _campaign(tmp_path)
    state = GitState(Path("/src/checkout"), "f" * 40, "main", 3, "git")
    t = provenance_table(c, ["d1"], state=state).set_index("item")
    assert list(t.columns) == ["value", "sha256"]
    assert t.loc["code", "value"].endswith(f"commit {'f' * 40} (branch main); uncommitted changes in 3 tracked files")
    for key in ("CPU", "logical cores", "memory", "OS"):
        assert t.loc[key, "value"] and t.loc[key, "value"] != "—"
    assert re.fullmatch(r"\d+( \(\d+ usable by this process\))?", t.loc["logical cores", "value"])
    assert t.loc["memory", "value"].endswith(" GiB")
    las = c / "flight_1.las"
    assert t.loc[str(las), "sha256"] == hashlib.sha256(las.read_bytes()).hexdigest()
    assert t.loc[str(las), "value"].endswith(f"({las.stat().st_size:,} bytes)")
    assert t.loc[str(c / "targets.csv")].tolist() == ["— (missing)", "—"]
    assert capsys.readouterr().err == ""  # quick hashing shows no progress bar


def test_report_opens_with_the_provenance_table_in_html_and_markdown(tmp_path, monkeypatch):
    res, cfg = _results(tmp_path)
    monkeypatch.setattr(provenance, "git_state", lambda: GitState(Path("/src/checkout"), "e" * 40, None, 0, "git"))
    out = run(res, res / "report" / "report.html", dict(cfg, datasets=["2010_12_1"]))
    md, page = out.markdown.read_text(), out.html.read_text()
    src = _section(md, "What this report ran on")
    assert "**Code, input data and machine" in src
    fields = res / "campaign" / "fields.csv"
    digest = hashlib.sha256(fields.read_bytes()).hexdigest()
    code = f"commit {'e' * 40}; no uncommitted changes in tracked files"
    for text in (src, page):
        assert code in text and digest in text and "logical cores" in text
    assert f"<td>{html.escape(str(fields))}</td>" in page
    assert f"| {res / 'campaign' / '2010_12_1.las'} | — (missing) | — |" in src


def test_the_report_runs_where_git_is_missing(tmp_path, monkeypatch):
    res, cfg = _results(tmp_path)
    monkeypatch.setattr(provenance.shutil, "which", lambda name: None)
    md = run(res, res / "report" / "report.html", cfg).markdown.read_text()
    line = next(x for x in _section(md, "What this report ran on").splitlines() if x.startswith("| code |"))
    assert "git not found" in line or "not a git checkout" in line


# -- Table 4: N is the number of pulses the accuracy was computed on ---------------------------

def test_table4_n_is_the_accuracys_and_the_left_out_pulses_are_said(tmp_path):
    res, cfg = _results(tmp_path)
    path = res / "classify" / "2012_10_1.json"
    r = json.loads(path.read_text())
    confusion = np.sum(r["main"]["one_pulse"]["resubstitution"]["confusion"])
    # a classify JSON of the earlier format: its top-level n_pulses also counted 3 pulses without E
    old = dict(r, n_pulses=r["n_pulses"] + 3, pulses_per_sample=(r["n_pulses"] + 3) / r["n_samples"])
    old["main"] = {k: v for k, v in r["main"].items() if k not in ("n_dropped", "dropped_reason")}
    path.write_text(json.dumps(old))
    assert table4([old]).loc[0, "n_pulses"] == confusion == r["n_pulses"]
    md = run(res, res / "report" / "report.html", cfg).markdown.read_text()
    line = (f"Left out of the classification, so not in its pulse counts: 2012_10_1 3 of {confusion + 3:,} pulses "
            "(no value of E or Apeak).")
    assert md.count(line) == 2  # in the summary and in the classification section
    assert f"| 2012_10_1 | {confusion} ({r['n_samples']}) |" in md
    assert pd.read_csv(res / "report" / "table4.csv").loc[0, "n_pulses"] == confusion


# -- the sensor study: each parameter's rows by value ------------------------------------------

def test_sensor_study_rows_go_by_value_in_every_table(tmp_path):
    res, cfg = _results(tmp_path)
    d = res / "sensor_study"
    # 0.5 appears under divergence before sampling's 0.25: grouping alone puts 0.5 first
    values = [("divergence_mrad", 0.5), ("divergence_mrad", 0.1), ("sampling_ns", 0.25), ("sampling_ns", 2.0),
              ("sampling_ns", 0.5), ("sampling_ns", 1.0)]
    pd.DataFrame([dict(parameter=p, value=v, level=lv, scheme=sc, accuracy=0.8, kappa=0.7, n=30)
                  for p, v in values for lv in ("1-pulse", "5-pulse")
                  for sc in ("resubstitution", "cross_validated")]).to_csv(d / "sensor_study.csv", index=False)
    pd.DataFrame([dict(parameter=p, value=v, species=sp, n=20, mean_Apeak=50.0)
                  for p, v in values for sp in ("birch", "fireweed")]).to_csv(d / "sensor_study_features.csv",
                                                                                 index=False)
    md = run(res, res / "report" / "report.html", cfg).markdown.read_text()
    body = _section(md, "Sensor parameters and three-species classification (Fig. 9; docs/method.md §(i3))")
    tables = [t for t in body.split("\n\n") if t.startswith("| parameter |")]
    assert len(tables) == 2
    for t in tables:
        rows = [[c.strip() for c in line.split("|")[1:3]] for line in t.splitlines()[2:]]
        order = list(dict.fromkeys((p, float(v)) for p, v in rows))
        assert order == [("divergence_mrad", 0.1), ("divergence_mrad", 0.5), ("sampling_ns", 0.25),
                         ("sampling_ns", 0.5), ("sampling_ns", 1.0), ("sampling_ns", 2.0)]
