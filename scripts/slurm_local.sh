#!/usr/bin/env bash
# A real single-node SLURM on this machine (munge + slurmctld + slurmd on localhost), for trying the
# `profiles/slurm` profile and for tests/test_slurm.py. Debian's slurm-wlm, no cgroups, no slurmdbd
# (so use `--slurm-status-command squeue`; see docs/howto/slurm.md).
#
# Usage (as root):  scripts/slurm_local.sh start|stop|status   (install: the apt step of start alone)
#   SLURM_LOCAL_DIR      scratch dir for state, spool, logs, PID files   [/tmp/spinecohort-slurm]
#   SLURM_LOCAL_TIMEOUT  seconds to wait for the node to come up idle    [60]
#   SLURM_LOCAL_FORCE=1  overwrite an /etc/slurm/slurm.conf this script did not write
#
# `start` installs the packages with apt when missing (apt cannot start services in containers:
# the daemons are started here directly), writes the one-node slurm.conf, starts the daemons and
# waits until `sinfo` shows the node idle. It records the PID of every daemon it started in the
# scratch dir; `stop` ends exactly those PIDs (a munged that was already running is left alone).
set -euo pipefail

D="${SLURM_LOCAL_DIR:-/tmp/spinecohort-slurm}"
TIMEOUT="${SLURM_LOCAL_TIMEOUT:-60}"
CONF=/etc/slurm/slurm.conf
MARKER="# written by spinecohort scripts/slurm_local.sh"
PACKAGES=(slurm-wlm munge)

log() { echo "slurm_local: $*" >&2; }
die() { log "error: $*"; exit 1; }

pid_alive() { [ -n "${1:-}" ] && kill -0 "$1" 2>/dev/null; }
read_pid() { [ -s "$1" ] && tr -dc '0-9' <"$1" || true; }

install_packages() {
    local missing=() pkg
    for pkg in "${PACKAGES[@]}"; do
        dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
    done
    [ ${#missing[@]} -eq 0 ] && return 0
    log "installing ${missing[*]} with apt"
    export DEBIAN_FRONTEND=noninteractive
    # update only when the package lists do not know the packages yet (saves ~5 s on a warm machine)
    apt-cache show "${missing[@]}" >/dev/null 2>&1 || apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
}

start_munge() {
    if munge -n 2>/dev/null | unmunge >/dev/null 2>&1; then
        log "munged already running; reusing it (will not stop it)"
        return 0
    fi
    mkdir -p /run/munge /var/log/munge /var/lib/munge
    chown munge: /run/munge /var/log/munge /var/lib/munge
    [ -s /etc/munge/munge.key ] || die "/etc/munge/munge.key missing (reinstall munge)"
    su -s /bin/sh munge -c /usr/sbin/munged
    local i
    for i in $(seq 50); do
        munge -n 2>/dev/null | unmunge >/dev/null 2>&1 && break
        sleep 0.1
    done
    munge -n | unmunge >/dev/null || die "munged does not answer (see /var/log/munge/munged.log)"
    cp /run/munge/munged.pid "$D/munged.pid"
}

write_conf() {
    local host cpus mem_mb
    host=$(hostname -s)
    getent hosts "$host" >/dev/null || die "hostname '$host' does not resolve (add it to /etc/hosts)"
    cpus=$(nproc)
    # leave ~1 GB to the OS and the daemons
    mem_mb=$(( $(free -m | awk '/^Mem:/ {print $2}') - 1024 ))
    if [ -e "$CONF" ] && ! grep -qF "$MARKER" "$CONF" && [ "${SLURM_LOCAL_FORCE:-0}" != 1 ]; then
        die "$CONF exists and was not written by this script (a real cluster?); set SLURM_LOCAL_FORCE=1 to overwrite"
    fi
    mkdir -p "$(dirname "$CONF")"
    cat >"$CONF" <<EOF
$MARKER (scratch dir $D)
ClusterName=spinecohort
SlurmctldHost=$host
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
StateSaveLocation=$D/state
SlurmdSpoolDir=$D/spool
SlurmctldPidFile=$D/slurmctld.pid
SlurmdPidFile=$D/slurmd.pid
SlurmctldLogFile=$D/log/slurmctld.log
SlurmdLogFile=$D/log/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MpiDefault=none
ReturnToService=2
# keep finished jobs visible to squeue/scontrol for an hour: snakemake's squeue status mode needs it
MinJobAge=3600
NodeName=$host CPUs=$cpus RealMemory=$mem_mb State=UNKNOWN
PartitionName=debug Nodes=$host Default=YES MaxTime=INFINITE State=UP
EOF
}

node_state() { sinfo -h -N -o '%t' 2>/dev/null | head -n1; }

cmd_start() {
    [ "$(id -u)" -eq 0 ] || die "must run as root (installs packages, starts daemons)"
    if pid_alive "$(read_pid "$D/slurmctld.pid")"; then
        die "slurmctld already running from $D (run: $0 stop)"
    fi
    local t0=$SECONDS
    install_packages
    # a second controller would fail on the port much later and less clearly
    if scontrol ping 2>/dev/null | grep -q UP; then
        die "a SLURM controller is already answering on this machine; stop it first"
    fi
    mkdir -p "$D/state" "$D/spool" "$D/log"
    write_conf
    # from here on, a failure stops whatever this start already launched
    trap 'log "start failed; stopping what was started"; cmd_stop' ERR
    start_munge
    slurmctld
    slurmd
    local state=""
    while [ $((SECONDS - t0)) -lt "$TIMEOUT" ]; do
        state=$(node_state)
        [ "$state" = idle ] && break
        sleep 0.5
    done
    if [ "$state" != idle ]; then
        log "node not idle after ${TIMEOUT}s (state '${state}'); tail of $D/log/slurmctld.log:"
        tail -n 20 "$D/log/slurmctld.log" >&2 || true
        cmd_stop
        exit 1
    fi
    log "SLURM up in $((SECONDS - t0)) s: node $(hostname -s) idle, partition debug, scratch $D"
}

stop_pid_file() {
    local name=$1 file="$D/$1.pid" pid i
    pid=$(read_pid "$file")
    if pid_alive "$pid"; then
        kill "$pid"
        for i in $(seq 50); do pid_alive "$pid" || break; sleep 0.1; done
        pid_alive "$pid" && { log "$name ($pid) ignores SIGTERM; sending SIGKILL"; kill -9 "$pid" || true; }
        log "stopped $name ($pid)"
    fi
    rm -f "$file"
}

cmd_stop() {
    # cancel leftover jobs (this private cluster only) so no slurmstepd outlives slurmd
    if pid_alive "$(read_pid "$D/slurmctld.pid")"; then
        local ids i
        ids=$(squeue -h -o %i 2>/dev/null || true)
        if [ -n "$ids" ]; then
            log "cancelling jobs: $(echo $ids)"
            scancel $ids 2>/dev/null || true
            for i in $(seq 50); do [ -z "$(squeue -h -t R,CG -o %i 2>/dev/null)" ] && break; sleep 0.2; done
        fi
    fi
    # slurmd first so it does not log a lost controller; munge last since both use it
    stop_pid_file slurmd
    stop_pid_file slurmctld
    stop_pid_file munged
    if [ -e "$CONF" ] && grep -qF "$MARKER (scratch dir $D)" "$CONF"; then rm -f "$CONF"; fi
}

cmd_status() {
    local name pid rc=0
    for name in munged slurmctld slurmd; do
        pid=$(read_pid "$D/$name.pid")
        if pid_alive "$pid"; then echo "$name: running (pid $pid)"; else echo "$name: not running (started by this script)"; rc=1; fi
    done
    if command -v sinfo >/dev/null && sinfo -h >/dev/null 2>&1; then sinfo -N; else echo "sinfo: controller not reachable"; rc=1; fi
    return $rc
}

case "${1:-}" in
    install) [ "$(id -u)" -eq 0 ] || die "must run as root"; install_packages ;;
    start) cmd_start ;;
    stop) cmd_stop ;;
    status) cmd_status ;;
    *) echo "usage: $0 start|stop|status|install" >&2; exit 2 ;;
esac
