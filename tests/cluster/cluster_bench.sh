#!/usr/bin/env bash
# Measures the cluster path (docs/BENCHMARKS.md "Cluster"), as root, on a one-node SLURM
# (tests/cluster/one_node_slurm.sh) on this machine:
#   0. what the machine gives a second worker process at all (build/bin/machine_bench);
#   1. per-job overhead: a chain of 8 single jobs running `true` (sbatch --dependency=afterok),
#      and the same 8 as Snakemake --slurm rules;
#   2. the vhp phantom (2048x1216, SLICES slices) through scripts/vispack-slurm with 1 and 2
#      workers (--shards 1 / 2, one CPU per array task), against vispack-run --threads 1;
#   3. the merge against a whole pack on the medium phantom (512x384x160, brick_edge 32: 5 slabs):
#      vispack-pack (whole) vs vispack-pack --slices per slab + vispack-merge (vispack-pack --merge
#      for a build without it), one thread.
# Usage: tests/cluster/cluster_bench.sh BIN_DIR [SLICES [BASE_ROOT]]   (default 16 slices)
#          BASE_ROOT: another checkout (its scripts/vispack-slurm and build/bin): its chains run in
#          the same rounds, interleaved, the order of the two reversed every other round (a chain
#          run right after a two-worker chain was seen 2-4 s slower: memory the two processes
#          freed is given back to this VM's host), each reported apart.
#        tests/cluster/cluster_bench.sh --merge-only BIN_DIR [BASELINE_BIN_DIR]
#          part 3 alone (no SLURM, no root); with a baseline, its runs alternate with BIN_DIR's
#          (A B A B), each printing its merge / whole ratio.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
merge_only=0
if [[ "${1:-}" == "--merge-only" ]]; then
  merge_only=1
  shift
fi
bin=$(cd "${1:?usage: cluster_bench.sh BIN_DIR [SLICES [BASE_ROOT]]}" && pwd)
slices=${2:-16}
base_root=""
if ((!merge_only)) && [[ -n "${3:-}" ]]; then
  base_root=$(cd "$3" && pwd)
  [[ -x $base_root/scripts/vispack-slurm && -x $base_root/build/bin/vispack-run ]] ||
    { echo "cluster_bench: $base_root has no scripts/vispack-slurm or build/bin"; exit 2; }
fi
bins=("$bin")
if ((merge_only)) && [[ -n "${2:-}" ]]; then bins+=("$(cd "$2" && pwd)"); fi
tmp=$(mktemp -d "${TMPDIR:-/tmp}/vispack-cluster-bench-XXXXXX")
if ((merge_only)); then
  trap 'rm -rf "$tmp"' EXIT
else
  [[ $(id -u) -eq 0 ]] || { echo "cluster_bench: needs root (it starts SLURM daemons)"; exit 77; }
  # shellcheck source=one_node_slurm.sh
  source "$root/tests/cluster/one_node_slurm.sh"
  trap 'stop_one_node_slurm; rm -rf "$tmp"' EXIT
fi
now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.2f", b - a }'; }
seconds_of() { sed -n 's/.*"seconds": *\([0-9.e+-]*\).*/\1/p' "$1" | head -n1; }

echo "machine: $(nproc) cores, $(awk '/MemTotal/ { printf "%.1f GiB", $2 / 1048576 }' /proc/meminfo), load average at start: $(cut -d' ' -f1-3 /proc/loadavg)"
echo "commit: $(git -C "$root" rev-parse --short HEAD)$(git -C "$root" diff --quiet HEAD -- . 2>/dev/null || echo ' (dirty tree)')"
if ((!merge_only)); then
# What the machine itself gives a second worker process (compute, fresh memory, memory reads):
# the ceiling the chain's 1 -> 2 workers speed-up is read against (~80 s).
if [[ -x $bin/machine_bench ]]; then
  "$bin/machine_bench" | sed 's/^/machine_bench: /'
else
  echo "machine_bench: not built in $bin (tests/bench); the machine's own ceiling not measured"
fi
start_one_node_slurm "$tmp/cluster"

# 1. Per-job overhead.
printf '#!/bin/bash\ntrue\n' >"$tmp/empty.sh"
t=$(now) previous=""
for i in $(seq 8); do
  args=(--parsable --kill-on-invalid-dep=yes -o /dev/null)
  [[ -n $previous ]] && args+=("--dependency=afterok:$previous")
  previous=$(sbatch "${args[@]}" "$tmp/empty.sh")
done
# Not sbatch --wait: it polls at 2, 10, 42, 74 s... (a 12 s chain reads as 42 s).
until scontrol -o show job "$previous" | grep -q 'JobState=COMPLETED'; do sleep 0.2; done
chain=$(elapsed "$t")
echo "overhead: 8 chained empty sbatch jobs: $chain s, $(awk -v c="$chain" 'BEGIN { printf "%.2f", c / 8 }') s per job"
mkdir -p "$tmp/snake"
{
  echo 'rule all:'
  echo '    input: "s8"'
  for i in $(seq 8); do
    echo "rule s$i:"
    ((i > 1)) && echo "    input: \"s$((i - 1))\""
    echo "    output: touch(\"s$i\")"
    echo '    shell: "true"'
  done
} >"$tmp/snake/Snakefile"
t=$(now)
(cd "$tmp/snake" && snakemake --quiet --slurm --jobs 1 --max-status-checks-per-second 1 \
   --default-resources slurm_partition=vispack runtime=10 mem_mb=100 >"$tmp/snake.out" 2>&1) ||
  { tail -n 30 "$tmp/snake.out"; echo "snakemake --slurm failed"; exit 1; }
snake=$(elapsed "$t")
echo "overhead: 8 chained empty Snakemake --slurm rules: $snake s, $(awk -v c="$snake" 'BEGIN { printf "%.2f", c / 8 }') s per job"

# 2. 1 and 2 workers on the vhp phantom.
# VISPACK_CLUSTER_BENCH_PHANTOM: a folder vispack-phantom --preset vhp --slices SLICES --seed 1
# already wrote (copied instead of generated again: ~2 minutes at 128 slices).
if [[ -n ${VISPACK_CLUSTER_BENCH_PHANTOM:-} ]]; then
  cp -a "$VISPACK_CLUSTER_BENCH_PHANTOM" "$tmp/vhp"
  rm -rf "$tmp/vhp/work" "$tmp/vhp/out" "$tmp/vhp/slurm"
else
  "$bin/vispack-phantom" --out "$tmp/vhp" --preset vhp --slices "$slices" --seed 1 --quiet >/dev/null
fi
cp -a "$tmp/vhp" "$tmp/local"
t=$(now)
"$bin/vispack-run" "$tmp/local/config.json" --quiet --threads 1 >/dev/null
local_s=$(elapsed "$t")
echo "vhp-$slices: vispack-run --threads 1: $local_s s"
# 1 and 2 workers alternate (1 2 1 2 ...), each run on a fresh copy of the phantom. The chain's
# time runs from the first sbatch to the moment vispack-slurm --wait sees the last job ended
# (scontrol every 0.5 s; sbatch --wait's own polling, 2, 10, 42, 74 s..., would add up to 32 s).
# Per step: SLURM's StartTime/EndTime of each job (1 s resolution; kept by MinJobAge).
reps=${VISPACK_CLUSTER_BENCH_REPS:-2}
declare -A walls=()
versions=(new)
[[ -n $base_root ]] && versions+=(base)
for rep in $(seq "$reps"); do
  order=("${versions[@]}")
  ((rep % 2 == 0 && ${#versions[@]} == 2)) && order=(base new)
  for w in 1 2; do
  for version in "${order[@]}"; do
    slurm_script=$root/scripts/vispack-slurm chain_bin=$bin
    [[ $version == base ]] && slurm_script=$base_root/scripts/vispack-slurm chain_bin=$base_root/build/bin
    rm -rf "$tmp/w$w"
    # Every chain starts from the same page cache: emptied (the copies of earlier chains filled
    # most of the memory, and a chain's allocations then reclaimed it as they went), then holding
    # the phantom and its fresh copy.
    sync
    echo 3 >/proc/sys/vm/drop_caches
    cp -a "$tmp/vhp" "$tmp/w$w"
    # The copy's dirty pages written back now, not by the kernel's flusher during the chain (on
    # two cores it takes the core a one-worker chain leaves free, and a two-worker chain's).
    sync
    t=$(now)
    "$slurm_script" "$tmp/w$w/config.json" --shards "$w" --bin "$chain_bin" \
      --jobs-dir "$tmp/w$w/jobs" --wait --poll 0.5 >"$tmp/w$w.out" 2>&1 || {
      # The failed chain's job logs are printed here: the temporary folder goes with the exit.
      cat "$tmp/w$w.out"
      for log in "$tmp/w$w/jobs/logs/"*; do [[ -s $log ]] && { echo "--- $log"; tail -n 20 "$log"; }; done
      exit 1
    }
    wall=$(elapsed "$t")
    walls[$version$w]+=" $wall"
    cmp -s "$tmp/local/out/volume.vpk" "$tmp/w$w/out/volume.vpk" || { echo "$version w$w: packed file differs"; exit 1; }
    ids=$(sed -n 's/^job IDs: //p' "$tmp/w$w.out")
    steps=""
    for id in $ids; do
      steps+=$(scontrol -o show job "$id" | awk '{
        for (i = 1; i <= NF; i++) { split($i, kv, "="); v[kv[1]] = kv[2] }
        cmd = "date -d " v["StartTime"] " +%s"; cmd | getline s; close(cmd)
        cmd = "date -d " v["EndTime"] " +%s"; cmd | getline e; close(cmd)
        if (e - s > m) m = e - s; name = v["JobName"] } END { sub("vispack-", "", name); printf " %s %ds", name, m }')
    done
    echo "vhp-$slices: rep $rep, $version, vispack-slurm --shards $w ($(ls "$tmp/w$w/jobs/"*.sh | wc -l) jobs): $wall s (byte-identical); longest task per step:$steps"
  done
  done
done
median() { tr ' ' '\n' | grep . | sort -g | awk '{ a[NR] = $1 } END { print (NR % 2) ? a[(NR + 1) / 2] : (a[NR / 2] + a[NR / 2 + 1]) / 2 }'; }
for version in "${versions[@]}"; do
  wall_1=$(median <<<"${walls[${version}1]}") wall_2=$(median <<<"${walls[${version}2]}")
  echo "vhp-$slices: $version: median of $reps: 1 worker $wall_1 s, 2 workers $wall_2 s; speed-up 1 -> 2 workers: $(awk -v a="$wall_1" -v b="$wall_2" 'BEGIN { printf "%.2f", a / b }')x (whole chain, SLURM's scheduling included)"
done
stop_one_node_slurm
fi

# 3. Merge against a whole pack (no SLURM needed).
"$bin/vispack-phantom" --out "$tmp/med" --preset medium --seed 1 --quiet >/dev/null
sed -i 's/"brick_edge": *[0-9]*/"brick_edge": 32/' "$tmp/med/config.json"
"$bin/vispack-run" "$tmp/med/config.json" --to labels --quiet >/dev/null
n=$("$bin/vispack-run" "$tmp/med/config.json" --plan | sed -n 's/^slices //p')
work=$(sed -n 's/.*"work_dir": *"\([^"]*\)".*/\1/p' "$tmp/med/config.json")
for rep in 1 2 3; do
for bin in "${bins[@]}"; do
  rm -rf "$tmp/med/$work/pack" "$tmp/med/$work/pack-slabs" "$tmp/med/out"
  t=$(now)
  "$bin/vispack-pack" --config "$tmp/med/config.json" --threads 1 --quiet
  whole=$(elapsed "$t")
  cp "$tmp/med/out/volume.vpk" "$tmp/whole.vpk"
  rm -rf "$tmp/med/$work/pack" "$tmp/med/out"
  t=$(now)
  for ((a = 0; a < n; a += 32)); do
    "$bin/vispack-pack" --config "$tmp/med/config.json" --slices "$a:$((a + 32))" --threads 1 --quiet
  done
  shards=$(elapsed "$t")
  t=$(now)
  if [[ -x $bin/vispack-merge ]]; then
    "$bin/vispack-merge" --config "$tmp/med/config.json" --threads 1 --quiet
  else
    "$bin/vispack-pack" --config "$tmp/med/config.json" --merge --threads 1 --quiet
  fi
  merge=$(elapsed "$t")
  cmp -s "$tmp/whole.vpk" "$tmp/med/out/volume.vpk" || { echo "merge differs"; exit 1; }
  echo "$(basename "$(dirname "$bin")")/$(basename "$bin"): medium (512x384x$n, brick 32): whole pack $whole s; $(((n + 31) / 32)) slab shards $shards s; merge $merge s = $(awk -v m="$merge" -v w="$whole" 'BEGIN { printf "%.0f", 100 * m / w }') % of the whole pack (byte-identical)"
done
done
