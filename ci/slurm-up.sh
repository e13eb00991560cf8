#!/usr/bin/env bash
# Bring up a one-node SLURM (slurmctld + slurmd on this host, munge auth) on a fresh Debian
# machine, as root, without systemd. Idempotent: a second call with the daemons up only waits
# for the node. Stop it with ci/slurm-down.sh, which kills only the PIDs recorded here.
#
#   sudo bash ci/slurm-up.sh        # then: sinfo; sbatch --wrap 'hostname'
#
# Environment: SLURM_PARTITION (default debug), SLURM_UP_TIMEOUT (seconds, default 60),
#              WAVEFOREST_SLURM_STATE (PID/state dir, default /run/waveforest-slurm).
set -euo pipefail

PARTITION="${SLURM_PARTITION:-debug}"
TIMEOUT="${SLURM_UP_TIMEOUT:-60}"
STATE="${WAVEFOREST_SLURM_STATE:-/run/waveforest-slurm}"
CONF_DIR=/etc/slurm
CONF="$CONF_DIR/slurm.conf"
LOG_DIR=/var/log/slurm
SPOOL_CTLD=/var/lib/slurm/slurmctld
SPOOL_D=/var/lib/slurm/slurmd

say() { echo "slurm-up: $*"; }
die() { echo "slurm-up: ERROR: $*" >&2; exit 1; }

[ "$(id -u)" -eq 0 ] || die "run as root (it installs packages and starts daemons)"

# --- 1. packages (Debian's slurm-wlm 22.05 and munge) -------------------------------------
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null \
   || ! command -v sbatch >/dev/null || ! command -v munged >/dev/null; then
    say "installing slurm-wlm and munge from Debian"
    # No init system here: keep the packages' maintainer scripts from starting services.
    policy_created=0
    if [ ! -e /usr/sbin/policy-rc.d ]; then
        printf '#!/bin/sh\nexit 101\n' > /usr/sbin/policy-rc.d
        chmod +x /usr/sbin/policy-rc.d
        policy_created=1
    fi
    export DEBIAN_FRONTEND=noninteractive
    if ! apt-get install -y -qq --no-install-recommends slurm-wlm munge >/tmp/slurm-up-apt.log 2>&1; then
        apt-get update -qq >/dev/null 2>&1 || true
        apt-get install -y -qq --no-install-recommends slurm-wlm munge >/tmp/slurm-up-apt.log 2>&1 \
            || { tail -20 /tmp/slurm-up-apt.log >&2; [ $policy_created = 1 ] && rm -f /usr/sbin/policy-rc.d; \
                 die "apt-get install slurm-wlm munge failed (log: /tmp/slurm-up-apt.log)"; }
    fi
    [ $policy_created = 1 ] && rm -f /usr/sbin/policy-rc.d
fi
say "$(slurmctld -V)"

mkdir -p "$STATE"

# True when the PID recorded in $STATE/$1.pid is alive and runs the program $1.
running() {
    local f="$STATE/$1.pid" pid
    [ -s "$f" ] || return 1
    pid=$(cat "$f")
    kill -0 "$pid" 2>/dev/null && [ "$(cat /proc/"$pid"/comm 2>/dev/null)" = "$1" ]
}

# --- 2. munge ------------------------------------------------------------------------------
id munge >/dev/null 2>&1 || die "user munge missing after install"
install -d -o munge -g munge -m 0700 /etc/munge /var/log/munge /var/lib/munge
install -d -o munge -g munge -m 0755 /run/munge
if [ ! -s /etc/munge/munge.key ]; then
    say "creating /etc/munge/munge.key"
    if command -v mungekey >/dev/null; then
        mungekey --create --keyfile=/etc/munge/munge.key --force
    else
        dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
    fi
fi
chown munge:munge /etc/munge/munge.key
chmod 0400 /etc/munge/munge.key

if ! running munged; then
    # munged runs as user munge and writes its PID file itself, so into a folder munge owns.
    rm -f "$STATE/munged.pid" "$STATE/munge/munged.pid"
    install -d -o munge -g munge -m 0755 "$STATE/munge"
    runuser -u munge -- munged --pid-file="$STATE/munge/munged.pid" --force \
        || { tail -20 /var/log/munge/munged.log >&2 2>/dev/null || true; die "munged did not start"; }
    for _ in $(seq 50); do [ -s "$STATE/munge/munged.pid" ] && break; sleep 0.1; done
    [ -s "$STATE/munge/munged.pid" ] || die "munged wrote no PID file (see /var/log/munge/munged.log)"
    cp "$STATE/munge/munged.pid" "$STATE/munged.pid"
fi
munge -n | unmunge >/dev/null || die "munge round trip failed (see /var/log/munge/munged.log)"

# --- 3. slurm.conf from `slurmd -C` ----------------------------------------------------------
NODE="$(hostname -s)"
install -d -m 0755 "$CONF_DIR"
install -d -o slurm -g slurm -m 0755 "$LOG_DIR" "$SPOOL_CTLD" "$SPOOL_D" /var/lib/slurm
# e.g. "NodeName=vm CPUs=2 Boards=1 SocketsPerBoard=1 CoresPerSocket=2 ThreadsPerCore=1 RealMemory=24000"
NODE_LINE="$(slurmd -C 2>/dev/null | head -1)"
case "$NODE_LINE" in NodeName=*) ;; *) die "slurmd -C printed no NodeName line: $NODE_LINE";; esac
NODE_LINE="NodeName=$NODE ${NODE_LINE#NodeName=* }"
# Leave 1 GiB of the node's memory to the OS and the workflow's own process.
MEM=$(sed -n 's/.*RealMemory=\([0-9]*\).*/\1/p' <<<"$NODE_LINE")
if [ -n "$MEM" ] && [ "$MEM" -gt 2048 ]; then
    NODE_LINE="$(sed "s/RealMemory=$MEM/RealMemory=$((MEM - 1024))/" <<<"$NODE_LINE")"
fi
NEW_CONF="$(mktemp)"
cat > "$NEW_CONF" <<CONF
# Written by waveforest ci/slurm-up.sh: a one-node cluster for CI, no accounting, no cgroups.
ClusterName=waveforest-ci
SlurmctldHost=$NODE
SlurmUser=slurm
SlurmdUser=root
AuthType=auth/munge
CryptoType=crypto/munge
MpiDefault=none
# cgroups cannot be delegated in this sandbox (no systemd): track processes via /proc instead.
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
# Cores are the only consumable resource (memory is not), so two 1-CPU jobs share the node.
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SchedulerType=sched/backfill
# No slurmdbd: the executor plugin must poll with squeue (slurm-status-command: squeue).
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
# One line per finished job (JobId, JobName = Snakemake's run id, state, times, node).
JobCompType=jobcomp/filetxt
JobCompLoc=$LOG_DIR/jobcomp.log
# Keep finished jobs visible to "squeue --states=all" for an hour: Snakemake's status polling
# (and a look at the run afterwards) reads them there.
MinJobAge=3600
ReturnToService=2
SlurmctldPort=6817
SlurmdPort=6818
StateSaveLocation=$SPOOL_CTLD
SlurmdSpoolDir=$SPOOL_D
SlurmctldPidFile=$STATE/slurmctld.pid
SlurmdPidFile=$STATE/slurmd.pid
SlurmctldLogFile=$LOG_DIR/slurmctld.log
SlurmdLogFile=$LOG_DIR/slurmd.log
SlurmctldDebug=info
SlurmdDebug=info
SlurmctldTimeout=60
SlurmdTimeout=60
InactiveLimit=0
KillWait=10
Waittime=0
$NODE_LINE State=UNKNOWN
PartitionName=$PARTITION Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
CONF
if ! cmp -s "$NEW_CONF" "$CONF"; then
    say "writing $CONF ($NODE_LINE)"
    install -m 0644 "$NEW_CONF" "$CONF"
    # Some settings (SelectType...) need a restart, so restart the daemons this script started.
    for d in slurmd slurmctld; do
        if running "$d"; then
            pid=$(cat "$STATE/$d.pid"); say "restarting $d (PID $pid) for the new slurm.conf"
            kill -TERM "$pid"
            for _ in $(seq 150); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
            kill -0 "$pid" 2>/dev/null && kill -KILL "$pid"
            rm -f "$STATE/$d.pid"
        fi
    done
fi
rm -f "$NEW_CONF"

# (no cgroup.conf: with proctrack/linuxproc and task/none, 22.05 slurmd does not need one)

dump_logs() {
    for f in "$LOG_DIR/slurmctld.log" "$LOG_DIR/slurmd.log" /var/log/munge/munged.log; do
        [ -e "$f" ] && { echo "----- tail $f" >&2; tail -40 "$f" >&2; }
    done
    sinfo -N -l >&2 2>/dev/null || true
}

# --- 4. daemons (each forks and writes the PID file named in slurm.conf) ---------------------
if ! running slurmctld; then
    rm -f "$STATE/slurmctld.pid"
    say "starting slurmctld"
    slurmctld -i || { dump_logs; die "slurmctld did not start"; }
fi
if ! running slurmd; then
    rm -f "$STATE/slurmd.pid"
    say "starting slurmd"
    slurmd || { dump_logs; die "slurmd did not start"; }
fi

# --- 5. wait for the node ----------------------------------------------------------------------
say "waiting up to ${TIMEOUT}s for $NODE to be idle in partition $PARTITION"
deadline=$((SECONDS + TIMEOUT))
while :; do
    state="$(sinfo -h -p "$PARTITION" -n "$NODE" -o '%t' 2>/dev/null | head -1 || true)"
    case "$state" in
        idle|mix|alloc) break ;;
        drain*|down*|fail*) scontrol update NodeName="$NODE" State=RESUME >/dev/null 2>&1 || true ;;
    esac
    if [ $SECONDS -ge $deadline ]; then
        dump_logs
        die "node $NODE not idle after ${TIMEOUT}s (state: '${state:-none}'); logs above"
    fi
    sleep 1
done
say "up: $(sinfo -h -o '%P %a %D %t %N %c CPUs')"
say "PIDs: munged $(cat "$STATE/munged.pid") slurmctld $(cat "$STATE/slurmctld.pid") slurmd $(cat "$STATE/slurmd.pid") (in $STATE)"
