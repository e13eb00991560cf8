"""The Snakemake workflow: lint-clean, and a dry run plans every stage for both configs."""

import shutil
import subprocess
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
