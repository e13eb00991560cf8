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
        "dataset,year,mean_range_m,pulse_width_fwhm_ns,footprint_diameter_m,sampling_ns,las_file,trajectory_file\n"
        + "".join(f"{d},{d[:4]},1200,7.2,0.18,1,{d}.las,{d}_trajectory.csv\n" for d in names))
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
    # only classify reads the other dataset's selection (Table 1's rule counts across datasets)
    assert not [j for j in jobs if "2010_12_1" in j[1] and j[0] != "classify"], jobs
    rules = {r for r, _ in jobs}
    assert {"ingest", "agc", "calibrate", "select", "simulate", "features_real", "classify"} <= rules
    assert "synthesize" not in rules and "sensitivity" not in rules  # they never read 2012_10_1.las


def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*") if p.is_file() and ".snakemake" not in p.parts}


@pytest.mark.parametrize("args", [["-n", "--cores", "2"], ["--lint"]])
def test_planning_writes_nothing(workdir, args):
    before = _files(workdir)
    res = _snakemake(*args, cwd=workdir)
    assert res.returncode == 0, res.stdout + res.stderr
    assert _files(workdir) == before, sorted(_files(workdir) - before)
    assert not (workdir / "results").exists()


def test_readme_override_of_a_nested_value(workdir):
    """README: --config 'campaign={"effects": {"understory": 1.5}}' (Snakemake hands the 1.5 over as
    a string); the stage config then holds the number, beside the config file's other keys."""
    override = 'campaign={"effects": {"understory": 1.5}, "samples_per_species": 3}'
    res = _snakemake("-n", "--cores", "2", "--config", override, cwd=workdir)
    assert res.returncode == 0, res.stdout + res.stderr
    res = _snakemake("--cores", "1", "results/config/synthesize.yaml", "--config", override, cwd=workdir)
    assert res.returncode == 0, res.stdout + res.stderr
    import yaml

    from waveforest import config

    written = config.load(workdir / "results/config/synthesize.yaml")
    assert written["campaign"]["effects"] == {"understory": 1.5}
    assert written["campaign"]["samples_per_species"] == 3 and written["seed"] == 2014
    assert yaml.safe_load((workdir / "results/config/synthesize.yaml").read_text()) == written  # complete
    bad = _snakemake("-n", "--cores", "2", "--config", 'campaign={"effects": {"understory": 1.5', cwd=workdir)
    assert bad.returncode != 0 and "--config campaign=" in bad.stdout + bad.stderr
    typo = _snakemake("-n", "--cores", "2", "--config", 'mcrt={"n_rayz": 5}', cwd=workdir)
    said = typo.stdout + typo.stderr
    errors = [line for line in said.splitlines() if line.startswith("waveforest: error:")]
    assert typo.returncode != 0 and len(errors) == 1, said
    assert errors[0].startswith("waveforest: error: --config on the command line: mcrt/n_rayz: unknown key; "
                                "expected one of n_rays, "), said
    assert "Traceback" not in said and "schema" not in said  # one line, not Snakemake's dump of the schema
    # a key given on the command line is blamed on it, not on the --configfile beside it
    typo = _snakemake("-n", "--cores", "2", "--configfile", "config/test/config.yaml", "--config", "dta=x",
                      cwd=workdir)
    said = typo.stdout + typo.stderr
    assert typo.returncode != 0, said
    assert "waveforest: error: --config on the command line: dta: unknown key" in said, said
    assert "config/test/config.yaml:" not in said, said


def test_config_change_reruns_exactly_the_stages_that_use_it(workdir):
    """Each stage's config file is rewritten only when a key it declares changes."""
    stages = ["agc", "calibrate", "select", "simulate", "features_real", "sensitivity", "report"]
    targets = [f"results/config/{s}.yaml" for s in stages]
    res = _snakemake("--cores", "1", *targets, cwd=workdir)
    assert res.returncode == 0, res.stdout + res.stderr
    assert not _planned_jobs(_snakemake("-n", "--cores", "1", *targets, cwd=workdir).stdout)
    res = _snakemake("-n", "--cores", "1", *targets, "--config", "agc={b: 0.01}", cwd=workdir)
    planned = {w for r, w in _planned_jobs(res.stdout + res.stderr) if r == "config"}
    assert planned == {"stage=agc", "stage=report"}, res.stdout + res.stderr
    res = _snakemake("-n", "--cores", "1", *targets, "--config", 'sensor={"cfd": {"fraction": 0.4}}', cwd=workdir)
    planned = {w for r, w in _planned_jobs(res.stdout + res.stderr) if r == "config"}
    # agc reads sensor/digitizer_max only, not the CFD (its keys are derived from its source)
    assert planned == {f"stage={s}" for s in ["calibrate", "simulate", "features_real", "sensitivity",
                                                "report"]}, res.stdout + res.stderr


def test_reference_dataset_comes_from_the_config(workdir):
    unquoted = _snakemake("-n", "--cores", "2", "--config", "reference_dataset=2012_10_1", cwd=workdir)
    assert unquoted.returncode != 0 and "set this key in a --configfile" in unquoted.stdout + unquoted.stderr
    (workdir / "ref.yaml").write_text("reference_dataset: '2012_10_1'\n")
    res = _snakemake("-n", "--cores", "2", "--configfile", "ref.yaml", cwd=workdir)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out
    jobs = _jobs_files(out)
    studies = [inputs for inputs, outputs in jobs if "results/sensitivity/sensitivity.csv" in outputs]
    assert studies and "results/calibration/2012_10_1.parquet" in studies[0], studies


def test_bad_user_campaign_is_one_line(workdir, tmp_path):
    """`data:` naming a folder without datasets.csv, or with a datasets.csv that fails its
    checks, stops planning with one line naming the file, not a traceback."""
    res = _snakemake("-n", "--cores", "2", "--config", f"data={tmp_path / 'nowhere'}", cwd=workdir)
    said = res.stdout + res.stderr
    errors = [line for line in said.splitlines() if line.startswith("waveforest: error:")]
    assert res.returncode != 0 and len(errors) == 1 and "nowhere/datasets.csv: no such file" in errors[0], said
    assert "Traceback" not in said and 'File "' not in said
    (tmp_path / "datasets.csv").write_text("dataset,year\n2010_12_1,2010\n")
    res = _snakemake("-n", "--cores", "2", "--config", f"data={tmp_path}", cwd=workdir)
    said = res.stdout + res.stderr
    errors = [line for line in said.splitlines() if line.startswith("waveforest: error:")]
    assert res.returncode != 0 and len(errors) == 1 and "missing column(s) mean_range_m" in errors[0], said
    assert not (workdir / "results").exists()
