#!/usr/bin/env bash
# .ci/slurm-test.sh KFMC - a sharded kfmc study on a real one-node Slurm cluster.
#
# Installs Slurm from Debian packages (munge, slurmctld, slurmd, slurm-client), starts the
# daemons on localhost without systemd (after ../shared/tools/slurm-local-cluster.sh), runs a
# study as a 4-task job array with the scripts `kfmc slurm` writes, merges it with the
# dependent merge job, asserts that the merged tables are byte-identical to one local
# process, and stops the daemons by the PIDs it started. Must run as root.
set -euo pipefail
cd "$(dirname "$0")/.."
KFMC_BIN=${1:-target/release/kfmc}

WORK=${SLURM_LOCAL_DIR:-$(mktemp -d)}   # everything Slurm writes goes here
NODE=localhost                                   # node name, independent of `hostname`

now()  { date +%s.%N; }
secs() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.1f", b - a }'; }
log()  { printf '[%s] %s\n' "$(date +%T)" "$*"; }

[ "$(id -u)" = 0 ] || { echo "must run as root" >&2; exit 2; }
rm -rf "$WORK"
mkdir -p "$WORK"/{state,spool,out}

# ---------------------------------------------------------------- install
T0=$(now)
export DEBIAN_FRONTEND=noninteractive
# There is no init system to start services, so keep the packages' postinst
# scripts from trying (only if the machine has no policy-rc.d of its own).
MADE_POLICY=0
if [ ! -e /usr/sbin/policy-rc.d ]; then
  printf '#!/bin/sh\nexit 101\n' >/usr/sbin/policy-rc.d
  chmod 0755 /usr/sbin/policy-rc.d
  MADE_POLICY=1
fi
apt-get update -q >"$WORK/apt.log" 2>&1
apt-get install -y -q --no-install-recommends \
  munge slurmctld slurmd slurm-client >>"$WORK/apt.log" 2>&1
[ "$MADE_POLICY" = 1 ] && rm -f /usr/sbin/policy-rc.d
T1=$(now)
log "install (apt-get update + install) took $(secs "$T0" "$T1") s"
dpkg-query -W -f='  ${Package} ${Version}\n' munge libmunge2 slurmctld slurmd \
  slurm-client slurm-wlm-basic-plugins

# ---------------------------------------------------------------- teardown
MUNGE_PID="" CTLD_PID="" SLURMD_PID=""
stop_pid() {   # stop_pid NAME PID : SIGTERM that PID, wait up to 20 s, then SIGKILL it
  local name=$1 pid=$2 i
  [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null || return 0
  kill -TERM "$pid" 2>/dev/null || true
  for i in $(seq 1 40); do kill -0 "$pid" 2>/dev/null || break; sleep 0.5; done
  if kill -0 "$pid" 2>/dev/null; then
    log "$name (pid $pid) ignored SIGTERM; sending SIGKILL"; kill -KILL "$pid" 2>/dev/null || true
  fi
  wait "$pid" 2>/dev/null || true
  log "stopped $name (pid $pid)"
}
teardown() {
  local rc=$?
  set +e
  if [ "$rc" != 0 ]; then
    log "FAILED (rc=$rc); last log lines:"
    for f in "$WORK"/slurmctld.log "$WORK"/slurmd.log /var/log/munge/munged.log; do
      [ -f "$f" ] && { echo "--- $f"; tail -n 20 "$f"; }
    done
  fi
  local t=$(now)
  stop_pid slurmd "$SLURMD_PID"
  stop_pid slurmctld "$CTLD_PID"
  stop_pid munged "$MUNGE_PID"
  log "teardown took $(secs "$t" "$(now)") s; total $(secs "$T0" "$(now)") s"
  exit "$rc"
}
trap teardown EXIT

# ---------------------------------------------------------------- munge
T2=$(now)
install -d -o munge -g munge -m 0700 /etc/munge /var/lib/munge /var/log/munge
install -d -o munge -g munge -m 0755 /run/munge
if [ ! -s /etc/munge/munge.key ]; then            # the package may have made one already
  dd if=/dev/urandom of=/etc/munge/munge.key bs=1024 count=1 status=none
fi
chown munge:munge /etc/munge/munge.key
chmod 0400 /etc/munge/munge.key
# setpriv exec()s munged, so $! is munged's own PID; -F keeps it in the foreground.
setpriv --reuid=munge --regid=munge --init-groups /usr/sbin/munged -F \
  >"$WORK/munged.stdout" 2>&1 &
MUNGE_PID=$!
for i in $(seq 1 50); do munge -n </dev/null 2>/dev/null | unmunge >/dev/null 2>&1 && break; sleep 0.2; done
munge -n </dev/null | unmunge | grep -E '^(STATUS|UID)'
log "munged up (pid $MUNGE_PID)"

# ---------------------------------------------------------------- slurm.conf
CPUS=$(nproc)
MEM_MB=$(( $(awk '/MemTotal/ { print $2 }' /proc/meminfo) / 1024 / 2 ))   # claim half the RAM
export SLURM_CONF="$WORK/slurm.conf"     # read by every slurm daemon and client below
cat >"$SLURM_CONF" <<EOF
ClusterName=kfmc-ci
SlurmctldHost=localhost
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
MpiDefault=none
MailProg=/bin/true
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerType=sched/backfill
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
ReturnToService=2
StateSaveLocation=$WORK/state
SlurmdSpoolDir=$WORK/spool
SlurmctldPidFile=$WORK/slurmctld.pid
SlurmdPidFile=$WORK/slurmd.pid
SlurmctldLogFile=$WORK/slurmctld.log
SlurmdLogFile=$WORK/slurmd.log
SlurmctldPort=6817
SlurmdPort=6818
NodeName=$NODE NodeAddr=127.0.0.1 CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=ci Nodes=$NODE Default=YES MaxTime=INFINITE State=UP
EOF

# ---------------------------------------------------------------- slurmctld + slurmd
# -D: stay in the foreground, so $! is the daemon's PID; -i: ignore old state.
/usr/sbin/slurmctld -D -i -f "$SLURM_CONF" >"$WORK/slurmctld.stdout" 2>&1 &
CTLD_PID=$!
for i in $(seq 1 60); do scontrol ping 2>/dev/null | grep -q UP && break; sleep 0.5; done
scontrol ping
/usr/sbin/slurmd -D -N "$NODE" -f "$SLURM_CONF" >"$WORK/slurmd.stdout" 2>&1 &
SLURMD_PID=$!
STATE=""
for i in $(seq 1 120); do
  STATE=$(sinfo -h -n "$NODE" -o %T 2>/dev/null || true)
  [ "$STATE" = idle ] && break
  sleep 0.5
done
[ "$STATE" = idle ] || { log "node state is '$STATE', not idle"; exit 1; }
T3=$(now)
log "start-up (munged + slurmctld + slurmd to node idle) took $(secs "$T2" "$T3") s"
log "slurmctld pid $CTLD_PID, slurmd pid $SLURMD_PID"
sinfo

# ---------------------------------------------------------------- the study
KFMC=$(readlink -f "$KFMC_BIN")
SPEC=$(readlink -f experiments/planar_seed_study.toml)
T4=$(now)
"$KFMC" run "$SPEC" --runs 20 --trace-runs 1 --quiet --out "$WORK/single"
"$KFMC" slurm "$SPEC" --shards 4 --runs 20 --cpus 1 --time 10 --out "$WORK/sharded"
cat "$WORK/sharded/slurm/array.sbatch"
# --wait on both submissions: the array, then the merge that depends on it.
timeout 600 bash "$WORK/sharded/slurm/submit.sh" --wait >"$WORK/submit.out" 2>&1 || {
  cat "$WORK/submit.out"; cat "$WORK"/sharded/slurm/*.out 2>/dev/null; exit 1; }
cat "$WORK/submit.out"
T5=$(now)
log "array of 4 parts + merge job took $(secs "$T4" "$T5") s"
"$KFMC" status "$WORK/sharded"
FAIL=0
for f in "$WORK"/single/*.parquet; do
  t=$(basename "$f")
  if cmp -s "$f" "$WORK/sharded/$t"; then echo "  $t: byte-identical"; else echo "  $t: DIFFERS"; FAIL=1; fi
done
n_single=$(ls "$WORK"/single/*.parquet | wc -l)
n_sharded=$(ls "$WORK"/sharded/*.parquet | wc -l)
[ "$n_single" = "$n_sharded" ] || { log "table counts differ: $n_single vs $n_sharded"; FAIL=1; }
[ "$FAIL" = 0 ] || { log "Slurm sharded study FAILED"; exit 1; }
log "Slurm sharded study PASSED: merged tables byte-identical to one process"
# the EXIT trap now stops slurmd, slurmctld and munged by the PIDs recorded above
