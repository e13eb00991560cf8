#!/usr/bin/env bash
# Stop the daemons that ci/slurm-up.sh started, by the PIDs it recorded; nothing else.
set -uo pipefail
STATE="${WAVEFOREST_SLURM_STATE:-/run/waveforest-slurm}"

stop() {  # stop NAME: TERM the recorded PID if it still runs NAME, wait up to 15 s, then KILL
    local name=$1 f="$STATE/$1.pid" pid
    [ -s "$f" ] || { echo "slurm-down: $name: no PID file, nothing to stop"; return 0; }
    pid=$(cat "$f")
    if ! kill -0 "$pid" 2>/dev/null || [ "$(cat /proc/"$pid"/comm 2>/dev/null)" != "$name" ]; then
        echo "slurm-down: $name: PID $pid not running"; rm -f "$f"; return 0
    fi
    kill -TERM "$pid"
    for _ in $(seq 150); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    if kill -0 "$pid" 2>/dev/null; then
        echo "slurm-down: $name: PID $pid ignored TERM, sending KILL"; kill -KILL "$pid" 2>/dev/null
    fi
    rm -f "$f"
    echo "slurm-down: $name (PID $pid) stopped"
}

# Jobs first (slurmd kills their steps when it stops), then the node, the controller, munge.
stop slurmd
stop slurmctld
stop munged
