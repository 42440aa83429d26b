#!/usr/bin/env bash
# A single-node Slurm on this machine, for trying and testing `wtbench sweep --executor slurm`.
#
#   scripts/slurm-local.sh start [DIR]   start munged, slurmctld and slurmd; prints the SLURM_CONF to export
#   scripts/slurm-local.sh stop  [DIR]   stop every daemon that `start` started (by the PIDs it recorded)
#
# It installs nothing: it needs the Debian packages slurm-wlm and munge (`apt-get install -y slurm-wlm munge`,
# as root; `.ci/run` does this). State, spool, logs and PID files live in DIR (default $SLURM_LOCAL_DIR or
# /tmp/wtbench-slurm); munge's key, socket and PID file in a fresh /tmp/wtbench-munge.* named in
# DIR/munge.dir. Every daemon listens on 127.0.0.1 only. Ports: $SLURM_LOCAL_PORT (slurmctld, default 6817)
# and the next one (slurmd). One node with CPUs=2 (or fewer when the machine has fewer) and a RealMemory
# below the machine's, partition `local`. Must run as root (SlurmUser=root).
set -euo pipefail

cmd=${1:-}
dir=${2:-${SLURM_LOCAL_DIR:-/tmp/wtbench-slurm}}
node=wtnode

die() {
  echo "error: slurm-local: $*" >&2
  exit 1
}

stop_pidfile() {
  # Kill the daemon whose PID the file records, if it is still that program; wait for it to go.
  local file=$1 name=$2 pid
  [ -f "$file" ] || return 0
  pid=$(cat "$file" 2>/dev/null || true)
  if [ -n "$pid" ] && [ -d "/proc/$pid" ] && grep -q "$name" "/proc/$pid/comm" 2>/dev/null; then
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 50); do
      [ -d "/proc/$pid" ] || break
      sleep 0.1
    done
    [ -d "/proc/$pid" ] && kill -9 "$pid" 2>/dev/null || true
  fi
  rm -f "$file"
}

case "$cmd" in
start)
  [ "$(id -u)" = 0 ] || die "must run as root (the cluster's SlurmUser is root)"
  for prog in munged slurmctld slurmd sinfo; do
    command -v "$prog" >/dev/null || die "$prog not found; install with: apt-get update && apt-get install -y slurm-wlm munge"
  done
  id munge >/dev/null 2>&1 || die "no 'munge' user; reinstall the munge package"
  if [ -f "$dir/slurmctld.pid" ] && [ -d "/proc/$(cat "$dir/slurmctld.pid")" ]; then
    die "a cluster already runs from $dir; run: $0 stop $dir"
  fi
  port=${SLURM_LOCAL_PORT:-6817}
  mkdir -p "$dir"/{state,spool}
  dir=$(cd "$dir" && pwd)

  # munge: a fresh key, owned by the munge user, which runs the daemon. Its folder is a fresh one in /tmp,
  # not inside DIR: the munge user may not be able to enter DIR's parents (pytest's are root-only).
  mdir=$(mktemp -d "/tmp/wtbench-munge.XXXXXX")
  echo "$mdir" >"$dir/munge.dir"
  chown munge:munge "$mdir"
  chmod 0700 "$mdir"
  dd if=/dev/urandom bs=1 count=1024 of="$mdir/munge.key" status=none
  chown munge:munge "$mdir/munge.key"
  chmod 0400 "$mdir/munge.key"
  sock=$mdir/munge.socket
  runuser -u munge -- munged --force --key-file="$mdir/munge.key" --socket="$sock" \
    --pid-file="$mdir/munged.pid" --log-file="$mdir/munged.log" --seed-file="$mdir/munged.seed" ||
    die "munged did not start; see $mdir/munged.log"
  for _ in $(seq 50); do
    [ -S "$sock" ] && break
    sleep 0.1
  done
  [ -S "$sock" ] || die "munged did not start; see $mdir/munged.log"

  cpus=$(nproc)
  [ "$cpus" -gt 2 ] && cpus=2
  mem_mib=$(awk '/MemTotal/ {print int($2 / 1024)}' /proc/meminfo)
  real=$((mem_mib / 2))
  [ "$real" -gt 8192 ] && real=8192
  cat >"$dir/slurm.conf" <<EOF
ClusterName=wtbench-local
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort=$port
SlurmdPort=$((port + 1))
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$sock
MpiDefault=none
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
ReturnToService=2
KillWait=2
InactiveLimit=0
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
NodeName=$node NodeAddr=127.0.0.1 NodeHostname=$node CPUs=$cpus RealMemory=$real State=UNKNOWN
PartitionName=local Nodes=$node Default=YES MaxTime=INFINITE State=UP
EOF
  export SLURM_CONF=$dir/slurm.conf
  slurmctld -f "$SLURM_CONF" || die "slurmctld did not start; see $dir/slurmctld.log"
  slurmd -f "$SLURM_CONF" -N "$node" || die "slurmd did not start; see $dir/slurmd.log"
  for _ in $(seq 100); do
    state=$(sinfo -h -n "$node" -o %t 2>/dev/null || true)
    case "$state" in idle | mix | alloc) break ;; esac
    sleep 0.2
  done
  case "$state" in
  idle | mix | alloc) ;;
  *) die "node $node is '${state:-unknown}', not idle; see $dir/slurmctld.log and $dir/slurmd.log" ;;
  esac
  echo "export SLURM_CONF=$SLURM_CONF"
  ;;
stop)
  [ -d "$dir" ] || exit 0
  stop_pidfile "$dir/slurmd.pid" slurmd
  stop_pidfile "$dir/slurmctld.pid" slurmctld
  if [ -f "$dir/munge.dir" ]; then
    mdir=$(cat "$dir/munge.dir")
    case "$mdir" in
    /tmp/wtbench-munge.*)
      stop_pidfile "$mdir/munged.pid" munged
      rm -rf "$mdir"
      ;;
    esac
    rm -f "$dir/munge.dir"
  fi
  ;;
*)
  echo "usage: $0 start|stop [DIR]" >&2
  exit 2
  ;;
esac
