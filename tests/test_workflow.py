"""The Snakemake workflow: lint-clean, and a dry run plans every stage for both configs."""

import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake not on PATH")


def _snakemake(*args, cwd):
    return subprocess.run(["snakemake", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.fixture()
def workdir(tmp_path):
    """A copy of the workflow files, so that planning writes nothing into the repo."""
    for name in ["Snakefile", "workflow", "config"]:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, tmp_path / name, symlinks=False)
        else:
            shutil.copy(src, tmp_path / name)
    return tmp_path


def test_lint_is_clean(workdir):
    res = _snakemake("--lint", cwd=workdir)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "good condition" in res.stdout + res.stderr


@pytest.mark.parametrize("configfile", [None, "config/test/config.yaml"])
def test_dry_run_plans_the_whole_study(workdir, configfile):
    args = ["-n", "--cores", "2"] + (["--configfile", configfile] if configfile else [])
    res = _snakemake(*args, cwd=workdir)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out
    for rule in ["synthesize", "ingest", "agc", "calibrate", "select", "simulate", "features_real",
                 "features_sim", "compare", "sensitivity", "sensor_study", "classify", "diagnose", "report"]:
        assert f"\n{rule} " in out or f"rule {rule}" in out, f"{rule} not planned"


def test_invalid_config_is_refused(workdir):
    bad = workdir / "bad.yaml"
    bad.write_text("mcrt: {n_rays: -5}\n")
    res = _snakemake("-n", "--cores", "1", "--configfile", str(bad), cwd=workdir)
    assert res.returncode != 0
    assert "n_rays" in res.stdout + res.stderr


def _planned_jobs(out: str) -> list[tuple[str, str]]:
    """(rule, wildcards) of every job of a verbose dry run."""
    jobs, rule = [], None
    for line in out.splitlines():
        s = line.strip()
        if s.startswith(("rule ", "localrule ")) and s.endswith(":"):
            rule = s.split()[1].rstrip(":")
            jobs.append((rule, ""))
        elif s.startswith("wildcards:") and rule is not None:
            jobs[-1] = (rule, s.split(":", 1)[1].strip())
    return jobs


def _jobs_files(out: str) -> list[tuple[list[str], list[str]]]:
    """(inputs, outputs) of every job of a verbose dry run."""
    jobs = []
    for line in out.splitlines():
        s = line.strip()
        if s.startswith(("rule ", "localrule ")) and s.endswith(":"):
            jobs.append(([], []))
        elif s.startswith(("input:", "output:")) and jobs:
            files = [f.strip() for f in s.split(":", 1)[1].split(",")]
            jobs[-1][0 if s.startswith("input") else 1].extend(files)
    return jobs


def _touch_in_dependency_order(workdir: Path, jobs, t0: float) -> None:
    """Create every output with a modification time after all of its job's inputs."""
    stamp: dict[str, float] = {}
    for _ in range(len(jobs)):  # longest chain is shorter than the number of jobs
        for inputs, outputs in jobs:
            t = max([stamp.get(f, t0) for f in inputs], default=t0) + 1
            for f in outputs:
                stamp[f] = t
    for f, t in stamp.items():
        p = workdir / f
        p.parent.mkdir(parents=True, exist_ok=True)
        p.touch()
        os.utime(p, (t, t))


def test_changing_one_datasets_input_reruns_only_what_depends_on_it(workdir):
    """A user campaign of two datasets: with every output up to date, a newer LAS file of one
    dataset replans that dataset's chain and the study-wide steps, never the other dataset's."""
    data = workdir / "data"
    data.mkdir()
    names = ["2010_12_1", "2012_10_1"]
    (data / "datasets.csv").write_text(
        "dataset,year,las_file,trajectory_file\n"
        + "".join(f"{d},{d[:4]},{d}.las,{d}_trajectory.csv\n" for d in names))
    for f in ["fields.csv", "targets.csv"] + [f"{d}.las" for d in names] + [f"{d}_trajectory.csv" for d in names]:
        (data / f).write_text("stand-in: only modification times matter in a dry run\n")
    t0 = time.time() - 10_000
    for f in data.iterdir():
        os.utime(f, (t0, t0))
    cfg = workdir / "user.yaml"
    cfg.write_text(f"data: {data}\ndatasets: {names}\nsimulate: {{datasets: {names}, chunks: 2}}\n")
    args = ["-n", "--cores", "2", "--configfile", str(cfg), "--rerun-triggers", "mtime"]

    first = _snakemake(*args, cwd=workdir)
    assert first.returncode == 0, first.stdout + first.stderr
    # make every planned output exist, each newer than its inputs (planned order is topological)
    _touch_in_dependency_order(workdir, _jobs_files(first.stdout + first.stderr), t0)
    assert not _planned_jobs(_snakemake(*args, cwd=workdir).stdout), "outputs should be up to date"

    os.utime(data / "2012_10_1.las")  # newer than everything
    res = _snakemake(*args, cwd=workdir)
    jobs = _planned_jobs(res.stdout + res.stderr)
    assert jobs, res.stdout + res.stderr
    assert not [j for j in jobs if "2010_12_1" in j[1]], jobs
    rules = {r for r, _ in jobs}
    assert {"ingest", "agc", "calibrate", "select", "simulate", "features_real", "classify"} <= rules
    assert "synthesize" not in rules and "sensitivity" not in rules  # they never read 2012_10_1.las
