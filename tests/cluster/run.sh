#!/usr/bin/env bash
# make test-cluster: starts a one-node Slurm cluster on this machine (Debian's slurm-wlm and
# munge, installed with apt-get when missing), runs a small sweep as a job array
# (`pipe sweep --executor slurm`), waits for it, merges it with `pipe sweep collect`, and
# checks that the table equals a local sweep of the same pipeline (every column but wall
# time and peak memory). Exits 0 with a SKIP message only where Slurm cannot be installed or
# started; any other failure exits 1. Stops the daemons it started (by their pids).
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/../.." && pwd)
PIPE=${PIPE:-$ROOT/target/release/pipe}
PIPELINE=$ROOT/tests/cluster/sweep.yaml
SWEEP_ARGS=(--vary pack.volume_fraction=0.1,0.2 --vary pack.max_attempts_per_sphere=200000,1
  --realizations 2 --collect phases.phases.volume_fraction --collect voxels.report.image_fraction
  --no-cache --quiet)

skip() { echo "SKIP test-cluster: $*"; exit 0; }
die() { echo "FAIL test-cluster: $*" >&2; exit 1; }

[ -x "$PIPE" ] || die "$PIPE not found (make build)"

if ! command -v slurmctld >/dev/null || ! command -v slurmd >/dev/null || ! command -v munged >/dev/null; then
  if [ "$(id -u)" != 0 ] || ! command -v apt-get >/dev/null; then
    skip "slurm-wlm and munge are not installed and cannot be (needs root and apt-get)"
  fi
  echo "installing slurm-wlm and munge (apt-get)..."
  export DEBIAN_FRONTEND=noninteractive
  apt-get install -y -qq slurm-wlm munge >/dev/null 2>&1 \
    || { apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq slurm-wlm munge >/dev/null 2>&1; } \
    || skip "apt-get install slurm-wlm munge failed"
fi
[ "$(id -u)" = 0 ] || skip "starting munged/slurmctld/slurmd for a private cluster needs root"

WORK=$(mktemp -d /tmp/grainpipe-cluster.XXXXXX)
chmod 755 "$WORK"  # munged runs as the munge user
STARTED=()
PASSED=0
cleanup() {
  # Stop only the daemons this script started, by pid (slurmd first).
  local k
  for ((k = ${#STARTED[@]} - 1; k >= 0; k--)); do
    [ -s "${STARTED[k]}" ] && kill "$(cat "${STARTED[k]}")" 2>/dev/null || true
  done
  sleep 1
  if [ "$PASSED" = 1 ]; then rm -rf "$WORK"; else echo "logs kept in $WORK"; fi
}
trap cleanup EXIT

# munge: an existing munged is reused; else one is started with a fresh key in $WORK.
MUNGE_SOCKET=/run/munge/munge.socket.2
if ! munge -n >/dev/null 2>&1; then
  mkdir -p "$WORK/munge" /run/munge
  dd if=/dev/urandom of="$WORK/munge/munge.key" bs=1024 count=1 status=none
  chmod 700 "$WORK/munge"; chmod 400 "$WORK/munge/munge.key"
  chown -R munge:munge "$WORK/munge" /run/munge 2>/dev/null || true
  if id munge >/dev/null 2>&1; then RUN_AS=(runuser -u munge --); else RUN_AS=(); fi
  "${RUN_AS[@]}" munged --key-file="$WORK/munge/munge.key" --socket="$MUNGE_SOCKET" \
    --pid-file="$WORK/munge/munged.pid" --log-file="$WORK/munge/munged.log" \
    --seed-file="$WORK/munge/munged.seed" \
    || skip "munged does not start here (see $WORK/munge/munged.log)"
  STARTED+=("$WORK/munge/munged.pid")
  for _ in $(seq 50); do munge -n >/dev/null 2>&1 && break; sleep 0.1; done
  munge -n >/dev/null 2>&1 || skip "munged started but does not answer"
fi

HOST=$(hostname -s)
CPUS=$(nproc)
MEM_MB=$(( $(awk '/MemTotal/ {print $2}' /proc/meminfo) / 1024 * 8 / 10 ))
mkdir -p "$WORK/state" "$WORK/spool"
cat > "$WORK/slurm.conf" <<CONF
ClusterName=grainpipe-test
SlurmctldHost=$HOST
SlurmctldPort=16817
SlurmdPort=16818
AuthType=auth/munge
CredType=cred/munge
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$WORK/state
SlurmdSpoolDir=$WORK/spool
SlurmctldPidFile=$WORK/slurmctld.pid
SlurmdPidFile=$WORK/slurmd.pid
SlurmctldLogFile=$WORK/slurmctld.log
SlurmdLogFile=$WORK/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
MpiDefault=none
ReturnToService=2
NodeName=$HOST CPUs=$CPUS RealMemory=$MEM_MB State=UNKNOWN
PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP
CONF
export SLURM_CONF=$WORK/slurm.conf

slurmctld -f "$SLURM_CONF" -i 2>"$WORK/slurmctld.err" || skip "slurmctld does not start here ($(tail -n 3 "$WORK/slurmctld.err" "$WORK/slurmctld.log" 2>/dev/null | tr '\n' ' '))"
STARTED+=("$WORK/slurmctld.pid")
slurmd -f "$SLURM_CONF" 2>"$WORK/slurmd.err" || skip "slurmd does not start here ($(tail -n 3 "$WORK/slurmd.err" "$WORK/slurmd.log" 2>/dev/null | tr '\n' ' '))"
STARTED+=("$WORK/slurmd.pid")

# Wait for the node to be idle.
for _ in $(seq 60); do
  state=$(sinfo -h -N -o '%T' 2>/dev/null | head -n 1 || true)
  [ "$state" = idle ] && break
  sleep 1
done
[ "${state:-}" = idle ] || skip "the one-node cluster did not come up (node state '${state:-none}'; see $WORK/slurmd.log)"
echo "one-node Slurm cluster up ($HOST, $CPUS CPUs, $MEM_MB MB)"

cd "$WORK"
"$PIPE" sweep "$PIPELINE" "${SWEEP_ARGS[@]}" --executor slurm --time 00:05:00 --out "$WORK/slurm" >"$WORK/submit.out" \
  || die "pipe sweep --executor slurm failed: $(cat "$WORK/submit.out")"
JOB=$(head -n 1 "$WORK/submit.out")
[ -n "$JOB" ] || die "no job id from sbatch"
grep -q '^#SBATCH --array=0-7$' "$WORK/slurm/sweep.sbatch" || die "unexpected array line in sweep.sbatch"
echo "submitted job array $JOB; waiting..."
for _ in $(seq 300); do
  [ -z "$(squeue -h -j "$JOB" 2>/dev/null)" ] && break
  sleep 1
done
[ -z "$(squeue -h -j "$JOB" 2>/dev/null)" ] || die "job $JOB still queued after 300 s: $(squeue -j "$JOB")"

"$PIPE" sweep collect "$WORK/slurm" || die "pipe sweep collect failed (missing results: see $WORK/slurm/runs/slurm-*.out)"
"$PIPE" sweep "$PIPELINE" "${SWEEP_ARGS[@]}" --jobs 2 --out "$WORK/local" || die "local sweep failed"

# Every column but the timings, which differ from run to run.
strip() {
  awk -F, 'NR == 1 { for (i = 1; i <= NF; i++) keep[i] = ($i !~ /^(wall_time|peak_memory)/) }
           { out = ""; for (i = 1; i <= NF; i++) if (keep[i]) out = out (out == "" ? "" : ",") $i; print out }' "$1"
}
if ! diff <(strip "$WORK/slurm/sweep.csv") <(strip "$WORK/local/sweep.csv"); then
  die "the Slurm table differs from the local one"
fi
ok=$(grep -c ',ok,' "$WORK/slurm/sweep.csv" || true)
failed=$(grep -c ',failed,' "$WORK/slurm/sweep.csv" || true)
[ "$ok" = 4 ] && [ "$failed" = 4 ] || die "expected 4 ok and 4 failed runs, got $ok and $failed"
echo "PASS test-cluster: job array $JOB ran 8 runs ($ok ok, $failed failed as designed); collect = local sweep"
PASSED=1
