#!/usr/bin/env bash
# A single-node SLURM cluster on this machine, from Debian's packages, for running the workflow
# through profiles/slurm (README, "Running on a cluster").
#
#   scripts/slurm_single_node.sh         install the packages if needed, write slurm.conf, start
#                                        munged, slurmctld and slurmd, wait until the node is idle
#   scripts/slurm_single_node.sh stop    stop the three daemons this script started (by PID file)
#
# Rerunnable: a daemon already running with the same slurm.conf is left alone. Needs root (it
# installs packages, writes /etc/slurm/slurm.conf and starts the daemons directly, since systemd is
# not running in a container). The cluster has no accounting database (the SLURM plugin then asks
# squeue for the jobs' states), tracks a job's processes by their parent PIDs and binds no tasks
# to cores (no cgroups are needed), and talks over the loopback address only.
set -euo pipefail

CONF_DIR=/etc/slurm
CONF="$CONF_DIR/slurm.conf"
STATE=/var/lib/slurm/slurmctld
SPOOL=/var/lib/slurm/slurmd
LOGS=/var/log/slurm
RUN=/run/slurm
MUNGE_RUN=/run/munge
WAIT_S=${SLURM_UP_TIMEOUT_S:-60}

die() { echo "slurm_single_node: $*" >&2; exit 1; }

pid_alive() { # pid_alive PIDFILE: the process named in PIDFILE is running (a zombie is not)
    local pid
    [[ -s "$1" ]] && pid=$(cat "$1") && [[ -r "/proc/$pid/stat" ]] \
        && [[ "$(cut -d ' ' -f 3 "/proc/$pid/stat")" != "Z" ]]
}

stop_daemon() { # stop_daemon PIDFILE NAME
    if pid_alive "$1"; then
        kill "$(cat "$1")"
        for _ in $(seq 50); do pid_alive "$1" || break; sleep 0.1; done
        pid_alive "$1" && die "$2 (PID $(cat "$1")) did not stop"
    fi
    rm -f "$1"
}

if [[ "${1:-}" == "stop" ]]; then
    stop_daemon "$RUN/slurmd.pid" slurmd
    stop_daemon "$RUN/slurmctld.pid" slurmctld
    stop_daemon "$MUNGE_RUN/munged.pid" munged
    exit 0
fi
[[ $# -eq 0 ]] || die "unknown argument '$1' (no argument starts the cluster, 'stop' stops it)"
[[ $(id -u) -eq 0 ]] || die "must run as root (it installs packages and starts the SLURM daemons)"

# --- packages ---------------------------------------------------------------------------------
if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v sinfo >/dev/null \
    || ! command -v munged >/dev/null; then
    echo "slurm_single_node: installing slurmctld, slurmd, slurm-client and munge"
    export DEBIAN_FRONTEND=noninteractive
    # the packages' scripts must not start the daemons (no slurm.conf yet): this script starts them
    policy=""
    if [[ ! -e /usr/sbin/policy-rc.d ]]; then
        policy=/usr/sbin/policy-rc.d
        printf '#!/bin/sh\nexit 101\n' >"$policy"
        chmod +x "$policy"
        trap 'rm -f "$policy"' EXIT
    fi
    apt-get update -q
    apt-get install -y -q slurmctld slurmd slurm-client munge
    [[ -z "$policy" ]] || { rm -f "$policy"; trap - EXIT; }
fi

# --- munge: the credentials slurmctld and slurmd exchange ------------------------------------
install -d -o munge -g munge -m 0700 /etc/munge /var/lib/munge /var/log/munge
install -d -o munge -g munge -m 0755 "$MUNGE_RUN"
if [[ ! -s /etc/munge/munge.key ]]; then
    dd if=/dev/urandom of=/etc/munge/munge.key bs=1 count=1024 status=none
fi
chown munge:munge /etc/munge/munge.key
chmod 0400 /etc/munge/munge.key
if ! pid_alive "$MUNGE_RUN/munged.pid"; then
    rm -f "$MUNGE_RUN/munged.pid" "$MUNGE_RUN/munge.socket.2"*
    runuser -u munge -- /usr/sbin/munged
fi
for _ in $(seq 50); do munge -n </dev/null >/dev/null 2>&1 && break; sleep 0.1; done
munge -n </dev/null | unmunge >/dev/null || die "munged does not answer (see /var/log/munge/munged.log)"

# --- slurm.conf: this host as controller and its one node, with its real CPUs and memory -------
HOST=$(hostname -s)
NODE_LINE=$(slurmd -C | sed -n 1p)   # NodeName=HOST CPUs=... RealMemory=... as slurmd sees them
[[ "$NODE_LINE" == NodeName=* ]] || die "slurmd -C did not describe this node: '$NODE_LINE'"
install -d -m 0755 "$CONF_DIR" "$STATE" "$SPOOL" "$LOGS" "$RUN"
NEW_CONF=$(cat <<EOF
# Written by scripts/slurm_single_node.sh: a single-node cluster for the calibration workflow.
ClusterName=single
SlurmctldHost=$HOST(127.0.0.1)
SlurmUser=root
SlurmctldPort=6817
SlurmdPort=6818
AuthType=auth/munge
StateSaveLocation=$STATE
SlurmdSpoolDir=$SPOOL
SlurmctldPidFile=$RUN/slurmctld.pid
SlurmdPidFile=$RUN/slurmd.pid
SlurmctldLogFile=$LOGS/slurmctld.log
SlurmdLogFile=$LOGS/slurmd.log
# no cgroups in a container: processes tracked by parent PID, tasks not bound to cores
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
ReturnToService=2
# no accounting database: sacct cannot answer, the plugin queries squeue, which keeps a finished
# job for MinJobAge seconds (the plugin needs at least 3 times its first status check interval)
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
MinJobAge=300
# jobs share the node by cores and memory
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
$NODE_LINE NodeAddr=127.0.0.1 State=UNKNOWN
PartitionName=main Nodes=$HOST Default=YES MaxTime=INFINITE State=UP
EOF
)
if [[ ! -f "$CONF" ]] || [[ "$(cat "$CONF")" != "$NEW_CONF" ]]; then
    printf '%s\n' "$NEW_CONF" >"$CONF"
    # a changed configuration: restart the daemons this script started
    stop_daemon "$RUN/slurmd.pid" slurmd
    stop_daemon "$RUN/slurmctld.pid" slurmctld
fi

# --- daemons ----------------------------------------------------------------------------------
if ! pid_alive "$RUN/slurmctld.pid"; then
    rm -f "$RUN/slurmctld.pid"
    slurmctld
fi
if ! pid_alive "$RUN/slurmd.pid"; then
    rm -f "$RUN/slurmd.pid"
    slurmd
fi

# --- wait for the node ------------------------------------------------------------------------
state=""
for _ in $(seq $((WAIT_S * 2))); do
    state=$(sinfo -h -N -n "$HOST" -o %T 2>/dev/null | head -n 1 || true)
    case "$state" in
        idle | mixed | allocated) break ;;
        down* | drain* | unknown*)
            scontrol update NodeName="$HOST" State=RESUME >/dev/null 2>&1 || true ;;
    esac
    sleep 0.5
done
case "$state" in
    idle | mixed | allocated) echo "slurm_single_node: node $HOST is $state ($NODE_LINE)" ;;
    *) die "node $HOST is '${state:-not listed}' after ${WAIT_S} s (see $LOGS/slurmctld.log and $LOGS/slurmd.log)" ;;
esac
