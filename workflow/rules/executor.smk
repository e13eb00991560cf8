# A run meant for SLURM (executor slurm, e.g. `--profile config/profiles/slurm`) on a machine
# without SLURM stops here with one line, also for a dry run (-n), instead of a dry run that
# passes or jobs that fail one by one at submission.
#
# The Snakefile is parsed before Snakemake picks its executor (workflow.executor_plugin is None
# here), so the intent is read from what a SLURM run sets: a slurm_* default resource (the
# profile's slurm_partition / slurm_account) or `--executor slurm` / `-e slurm` on the command
# line. Jobs running on a node (exec mode remote/subprocess) skip the check.
import shutil as _shutil
import sys as _sys


def _slurm_intended():
    argv = _sys.argv[1:]
    for i, arg in enumerate(argv):
        if arg in ("--executor", "-e") and i + 1 < len(argv) and argv[i + 1] == "slurm":
            return True
        if arg == "--executor=slurm":
            return True
    default_resources = workflow.resource_settings.default_resources
    names = [str(a).split("=", 1)[0].strip() for a in (getattr(default_resources, "args", None) or [])]
    return any(name.startswith("slurm_") for name in names)


if workflow.is_main_process and _slurm_intended():
    _missing = [cmd for cmd in ("sbatch", "squeue") if _shutil.which(cmd) is None]
    if _missing:
        _sys.exit(
            f"waveforest: this run is set up for SLURM (executor slurm, e.g. the profile "
            f"config/profiles/slurm) but {' and '.join(_missing)} {'is' if len(_missing) == 1 else 'are'} "
            f"not on PATH: run it on a "
            f"SLURM login node, or locally with --profile config/profiles/local"
        )
