#!/usr/bin/env bash
# The smoke study through SLURM: the project's profile plus the CI overlay, then the smoke checks.
#
#   bash ci/slurm-up.sh                      # a one-node SLURM (root); ci/slurm-down.sh stops it
#   bash ci/smoke-slurm.sh [OUT_DIR]         # from the repository root
#
# The workflow writes results/ (its fixed output folder), which must not exist yet: otherwise
# Snakemake would find the outputs of an earlier run up to date and submit nothing. After
# the run, tests/smoke_check.py checks results/; with OUT_DIR given, results/ is then moved
# there (e.g. results-slurm, to compare with a local run: python ci/compare-results.py A B).
# Prints the jobs SLURM ran per rule and the wall time. Kept in .snakemake/: the snakemake
# output (smoke-slurm.log) and every job of the run (smoke-slurm-jobs.txt); each job's SLURM
# log is under .snakemake/slurm_logs/. Extra arguments for snakemake go in SMOKE_SLURM_ARGS.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT="${1:-results}"

command -v sbatch >/dev/null && command -v squeue >/dev/null \
    || { echo "smoke-slurm: no SLURM on PATH: run ci/slurm-up.sh first" >&2; exit 1; }
# (results/config.yaml alone is what parsing the workflow writes, e.g. by a dry run)
if [ -e results ] && [ -n "$(ls -A results | grep -vx config.yaml)" ]; then
    echo "smoke-slurm: results/ exists; move it away first (e.g. mv results results-local)" >&2
    exit 1
fi
if [ "$OUT" != results ] && [ -e "$OUT" ]; then
    echo "smoke-slurm: $OUT exists already" >&2; exit 1
fi

mkdir -p .snakemake
start=$(date +%s)
# shellcheck disable=SC2086
snakemake --profile config/profiles/slurm --profile config/profiles/slurm-ci \
    --configfile config/test/config.yaml ${SMOKE_SLURM_ARGS:-} 2>&1 | tee .snakemake/smoke-slurm.log
rc=${PIPESTATUS[0]}
end=$(date +%s)
run_id=$(sed -n 's/^SLURM run ID: //p' .snakemake/smoke-slurm.log | tail -1)

if [ -n "$run_id" ]; then
    # Every job of the run, for a later look (jobid, rule and wildcards, state, CPUs, times).
    { echo "jobid|comment|state|cpus|elapsed|start|end"
      squeue --states=all --noheader --name "$run_id" --format '%i|%k|%T|%C|%M|%S|%e' | sort -n
    } > .snakemake/smoke-slurm-jobs.txt
    echo "smoke-slurm: SLURM jobs of run $run_id per rule (all in .snakemake/smoke-slurm-jobs.txt):"
    squeue --states=all --noheader --name "$run_id" --format '%k %T' \
        | sed 's/^rule_\([A-Za-z0-9_]*\)_wildcards_[^ ]* /\1 /; s/^rule_\([A-Za-z0-9_]*\) /\1 /' \
        | sort | uniq -c | awk '{printf "  %-14s %-10s %d\n", $2, $3, $1}'
fi
[ "$rc" -eq 0 ] || { echo "smoke-slurm: snakemake failed (exit $rc); SLURM logs in .snakemake/slurm_logs/" >&2; exit "$rc"; }

python tests/smoke_check.py results config/test/config.yaml
[ "$OUT" = results ] || mv results "$OUT"
echo "smoke-slurm: wall time $((end - start)) s (snakemake through SLURM; results in $OUT)"
