# A one-node SLURM for tests and benchmarks, sourced by tests/cluster/*.sh (bash):
#   source tests/cluster/one_node_slurm.sh
#   trap stop_one_node_slurm EXIT
#   start_one_node_slurm DIR      # DIR: an empty temporary folder (state, spool, logs, key)
# starts munged (its own key, socket folder, PID and log files under DIR), slurmctld -D -c -i and
# slurmd -D bound to 127.0.0.1 on two free ports (no systemd; ProctrackType=proctrack/linuxproc,
# TaskPlugin=task/none, no accounting, CommunicationParameters=NoCtldInAddrAny,NoInAddrAny,
# SlurmUser=root, SchedulerParameters=batch_sched_delay=0: see below), exports SLURM_CONF and
# USER, and waits until the node is idle (partition "vispack", node "vispack0", all CPUs, half
# the memory). Needs root. Returns 1 (with the daemons' output) if the cluster does not come
# up. stop_one_node_slurm stops every daemon it started, by PID (TERM, then KILL after 5 s),
# and prints the daemons' log tails when ONE_NODE_SLURM_SHOW_LOGS=1.
one_node_slurm_pids=()
one_node_slurm_dir=""

stop_one_node_slurm() {
  local pid i
  for ((i = ${#one_node_slurm_pids[@]} - 1; i >= 0; i--)); do
    kill -TERM "${one_node_slurm_pids[$i]}" 2>/dev/null || true
  done
  for pid in "${one_node_slurm_pids[@]}"; do
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill -KILL "$pid" 2>/dev/null || true
  done
  one_node_slurm_pids=()
  if [[ ${ONE_NODE_SLURM_SHOW_LOGS:-0} == 1 && -n $one_node_slurm_dir ]]; then
    local log
    for log in "$one_node_slurm_dir"/{slurmctld,slurmd,munged}.log; do
      [[ -f $log ]] && { echo "--- last lines of $log"; tail -n 15 "$log"; }
    done
  fi
  return 0
}

start_one_node_slurm() {
  local dir=$1 socket ctld_port slurmd_port cpus memory state
  one_node_slurm_dir=$dir
  mkdir -p "$dir/munge" "$dir/state" "$dir/spool"
  chmod 700 "$dir/munge"
  dd if=/dev/urandom of="$dir/munge/munge.key" bs=1024 count=1 status=none
  chmod 400 "$dir/munge/munge.key"
  socket=$dir/munge/munge.socket
  munged -F -f --key-file="$dir/munge/munge.key" --socket="$socket" \
    --pid-file="$dir/munge/munged.pid" --log-file="$dir/munged.log" \
    --seed-file="$dir/munge/munged.seed" >"$dir/munged.out" 2>&1 &
  one_node_slurm_pids+=($!)
  for _ in $(seq 50); do [[ -S $socket ]] && break; sleep 0.1; done
  [[ -S $socket ]] || { cat "$dir/munged.out"; echo "munged did not start"; return 1; }

  port_free() { ! ss -Htan "sport = :$1" | grep -q .; }
  for _ in $(seq 50); do
    ctld_port=$((20000 + RANDOM % 20000)) slurmd_port=$((ctld_port + 1))
    port_free "$ctld_port" && port_free "$slurmd_port" && break
  done
  cpus=$(nproc)
  memory=$(awk '/MemTotal/ { printf "%d", $2 / 1024 / 2 }' /proc/meminfo)
  # batch_sched_delay=0: SLURM's default (3 s) lets the scheduler wait up to 3 s after its last
  # run before it starts a batch job, so a dependent step whose array tasks ended at different
  # moments started 2.5-3 s after the last one here (slurmctld's debug log: the job complete at
  # .697, the next scheduler run 2.8 s later), against 0.2-0.5 s with 0. A site's own setting
  # is its business; the test cluster measures vispack, not that throttle (docs/BENCHMARKS.md).
  cat >"$dir/slurm.conf" <<EOF
ClusterName=vispacktest
SlurmctldHost=localhost(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$slurmd_port
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$socket
CommunicationParameters=NoCtldInAddrAny,NoInAddrAny
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
SchedulerType=sched/builtin
SchedulerParameters=batch_sched_delay=0
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
MpiDefault=none
ReturnToService=2
SlurmdTimeout=60
InactiveLimit=0
KillWait=5
MinJobAge=600
NodeName=vispack0 NodeAddr=127.0.0.1 NodeHostname=$(hostname) CPUs=$cpus RealMemory=$memory State=UNKNOWN
PartitionName=vispack Nodes=vispack0 Default=YES MaxTime=INFINITE State=UP OverSubscribe=NO
EOF
  export SLURM_CONF=$dir/slurm.conf
  export USER=${USER:-$(id -un)}  # Snakemake 7.21's SLURM executor reads it
  slurmctld -D -c -i -f "$SLURM_CONF" >"$dir/slurmctld.out" 2>&1 &
  one_node_slurm_pids+=($!)
  slurmd -D -N vispack0 -f "$SLURM_CONF" >"$dir/slurmd.out" 2>&1 &
  one_node_slurm_pids+=($!)
  state=""
  for _ in $(seq 150); do
    state=$(sinfo -h -n vispack0 -o %T 2>/dev/null || true)
    [[ $state == idle ]] && break
    sleep 0.2
  done
  if [[ $state != idle ]]; then
    cat "$dir/slurmctld.out" "$dir/slurmd.out"
    echo "the one-node cluster did not come up (node state '$state')"
    return 1
  fi
  echo "cluster up: slurmctld :$ctld_port, slurmd :$slurmd_port, $cpus CPUs, munge socket $socket"
}
