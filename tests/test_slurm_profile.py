"""The SLURM profile, its CI overlay, the no-SLURM check and the table comparison (fast).

The SLURM run itself is ci/smoke-slurm.sh (needs ci/slurm-up.sh); these tests need no SLURM.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PROFILE = ROOT / "config" / "profiles" / "slurm" / "config.yaml"
CI_PROFILE = ROOT / "config" / "profiles" / "slurm-ci" / "config.yaml"
SLURM_COMMANDS = {"sbatch", "squeue", "sinfo", "sacct", "sacctmgr", "scontrol", "scancel", "srun", "sshare"}
NODE_CPUS = 2  # the one-node cluster of ci/slurm-up.sh on CI's 2-core machine


def _load(path: Path) -> dict:
    data = yaml.safe_load(path.read_text())
    assert isinstance(data, dict), f"{path}: not a YAML mapping"
    return data


def _rules() -> set[str]:
    names = set()
    for smk in (ROOT / "workflow" / "rules").glob("*.smk"):
        names |= set(re.findall(r"^\s*rule (\w+):", smk.read_text(), flags=re.M))
    return names


def _merged() -> dict:
    """The two profiles as Snakemake merges them: the later one replaces whole top-level keys."""
    return {**_load(PROFILE), **_load(CI_PROFILE)}


def test_profile_is_slurm_and_documents_every_setting_to_adapt():
    prof = _load(PROFILE)
    text = PROFILE.read_text()
    assert prof["executor"] == "slurm"
    res = prof["default-resources"]
    for key in ("slurm_partition", "slurm_account", "runtime", "mem_mb", "cpus_per_task"):
        assert key in res, f"default-resources lacks {key}"
    assert prof["slurm-status-command"] in ("sacct", "squeue")
    assert "slurm-init-seconds-before-status-checks" in prof
    adapt = [line for line in text.splitlines() if "ADAPT" in line]
    for what in ("partition", "account", "CPUs per task", "status command"):
        assert any(what in line for line in adapt), f"no ADAPT comment on {what}"
    assert "snakemake-executor-plugin-slurm" in text
    assert "benchmarks" in text  # resources are sized from results/benchmarks/


def test_profile_names_only_real_rules():
    rules = _rules()
    for prof in (_load(PROFILE), _load(CI_PROFILE)):
        for key in ("set-resources", "set-threads"):
            unknown = set(prof.get(key) or {}) - rules
            assert not unknown, f"{key} names no rule of the workflow: {sorted(unknown)}"


def test_ci_overlay_fits_the_one_node_cluster():
    ci = _load(CI_PROFILE)
    merged = _merged()
    assert merged["executor"] == "slurm"
    assert merged["slurm-status-command"] == "squeue"  # no slurmdbd on the CI cluster
    assert merged["slurm-init-seconds-before-status-checks"] <= 10
    assert merged["slurm-no-account"] is True
    res = merged["default-resources"]
    assert res["slurm_partition"] == "debug"
    assert "slurm_account" not in res
    # CPUs per task follow threads: every multi-threaded rule of the real profile is brought
    # down to the node's CPUs (a job asking for more stays PENDING forever).
    assert set(_load(PROFILE).get("set-threads") or {}) <= set(ci["set-threads"])
    assert all(1 <= n <= NODE_CPUS for n in merged["set-threads"].values())
    for rule, res_rule in (merged.get("set-resources") or {}).items():
        assert int(res_rule.get("cpus_per_task", 1)) <= NODE_CPUS, rule
    # CI runs the real profile with the overlay on top, never an edited copy of it.
    script = (ROOT / "ci" / "smoke-slurm.sh").read_text()
    assert "--profile config/profiles/slurm --profile config/profiles/slurm-ci" in script
    assert "sed -i" not in script


def _compare_module():
    spec = importlib.util.spec_from_file_location("compare_results", ROOT / "ci" / "compare-results.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_compare_results_by_content(tmp_path):
    cmp = _compare_module()
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b, a / "benchmarks", b / "benchmarks"):
        d.mkdir(parents=True)
    df = pd.DataFrame({"x": [1.0, 2.5, float("nan")], "k": ["p", "q", "r"]})
    df.to_parquet(a / "t.parquet")
    df[["k", "x"]].to_parquet(b / "t.parquet")  # column order is not meaningful
    df.to_csv(a / "t.csv", index=False)
    df.to_csv(b / "t.csv", index=False)
    (a / "benchmarks" / "r.tsv").write_text("s\n1.0\n")  # timings are skipped
    (b / "benchmarks" / "r.tsv").write_text("s\n2.0\n")
    assert cmp.compare(a, b) == []
    assert cmp.main([str(a), str(b)]) == 0

    df.assign(x=[1.0, 2.5000001, float("nan")]).to_parquet(b / "t.parquet")
    (b / "only.csv").write_text("a\n1\n")
    fails = cmp.compare(a, b)
    assert any(f.startswith("t.parquet") for f in fails)
    assert any(f.startswith("only.csv") and "only in" in f for f in fails)
    assert cmp.main([str(a), str(b)]) == 1


def test_snakefile_includes_the_executor_check():
    text = (ROOT / "Snakefile").read_text()
    assert 'include: "workflow/rules/executor.smk"' in text


@pytest.mark.timeout(120)
def test_slurm_profile_without_slurm_fails_with_one_line(tmp_path):
    """`snakemake --profile config/profiles/slurm -n` where sbatch/squeue are missing."""
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        pytest.skip("snakemake-executor-plugin-slurm not installed (pip install -e '.[slurm]')")
    snakemake = shutil.which("snakemake") or str(Path(sys.executable).parent / "snakemake")
    # A copy of the workflow, so that nothing is written into the repository; the check is
    # included as the Snakefile does.
    for name in ("workflow", "config"):
        shutil.copytree(ROOT / name, tmp_path / name)
    snakefile = (ROOT / "Snakefile").read_text()
    if "executor.smk" not in snakefile:
        snakefile = snakefile.replace(
            'include: "workflow/rules/common.smk"',
            'include: "workflow/rules/executor.smk"\ninclude: "workflow/rules/common.smk"',
        )
    (tmp_path / "Snakefile").write_text(snakefile)
    # PATH: a folder of links to every command on PATH except SLURM's.
    bindir = tmp_path / "bin"
    bindir.mkdir()
    for folder in [str(Path(snakemake).parent), *os.environ.get("PATH", "").split(os.pathsep)]:
        if not os.path.isdir(folder):
            continue
        for name in os.listdir(folder):
            if name in SLURM_COMMANDS or (bindir / name).exists():
                continue
            (bindir / name).symlink_to(os.path.join(folder, name))
    env = {**os.environ, "PATH": str(bindir)}
    env.pop("SNAKEMAKE_PROFILE", None)
    proc = subprocess.run(
        [snakemake, "--profile", "config/profiles/slurm", "-n"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=110,
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = [ln for ln in (proc.stdout + proc.stderr).splitlines() if ln.strip()]
    lines = [ln for ln in lines if not ln.startswith("Using profile")]
    assert len(lines) == 1, lines
    assert "SLURM" in lines[0] and "sbatch" in lines[0] and "Traceback" not in lines[0]
    assert not (tmp_path / "results").exists()
