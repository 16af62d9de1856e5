#!/usr/bin/env bash
# What a second worker costs on this machine, without SLURM (docs/BENCHMARKS.md "Cluster"): each
# sharded step of the chain on the two halves of a stack, first one after the other, then both
# at once, one thread each; prints each step's times and the speed-up two workers could reach
# at best ((alone + alone) / wall at once); first, the same for plain workloads (build/bin/
# machine_bench: compute, fresh memory, memory reads), the machine's own ceiling. As root only
# for emptying the page cache first.
# Usage: tests/cluster/shards_at_once.sh BIN_DIR PHANTOM_DIR
#   PHANTOM_DIR: a folder vispack-phantom wrote (e.g. --preset vhp --slices 256 --seed 1); its
#   inputs are linked, not copied, into a temporary work folder.
set -euo pipefail
bin=$(cd "${1:?usage: shards_at_once.sh BIN_DIR PHANTOM_DIR}" && pwd)
phantom=$(cd "${2:?usage: shards_at_once.sh BIN_DIR PHANTOM_DIR}" && pwd)
d=$(mktemp -d "${TMPDIR:-/tmp}/vispack-shards-at-once-XXXXXX")
trap 'rm -rf "$d"' EXIT
cp "$phantom/config.json" "$phantom/palette.json" "$d/"
for x in rgb ct seg; do [[ -e $phantom/$x ]] && ln -s "$phantom/$x" "$d/$x"; done
n=$("$bin/vispack-run" "$d/config.json" --plan | sed -n 's/^slices //p')
half=$((n / 2))
if [[ $(id -u) -eq 0 ]]; then
  sync
  echo 3 >/proc/sys/vm/drop_caches
fi
cat "$phantom"/{rgb,ct,seg}/* >/dev/null 2>&1 || true  # the inputs in the page cache, as in a chain
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.2f", b - a }'; }
one() { local s; s=$(now); "$@" --threads 1 --quiet --force >/dev/null; since "$s"; }
step() {  # NAME COMMAND...: the command run on [0, half) and [half, n)
  local name=$1 a b p q s wall
  shift
  a=$(one "$@" --slices "0:$half")
  b=$(one "$@" --slices "$half:$n")
  s=$(now)
  one "$@" --slices "0:$half" >"$d/first" &
  q=$(one "$@" --slices "$half:$n")
  wait
  wall=$(since "$s")
  p=$(cat "$d/first")
  echo "$name: alone $a + $b s; at once $p, $q s (wall $wall): $(awk -v a="$a" -v b="$b" -v p="$p" -v q="$q" 'BEGIN { printf "%+.0f", 100 * ((p + q) / (a + b) - 1) }') % per shard; two workers at best $(awk -v a="$a" -v b="$b" -v w="$wall" 'BEGIN { printf "%.2f", (a + b) / w }')x"
}
echo "machine: $(nproc) cores, load average at start: $(cut -d' ' -f1-3 /proc/loadavg); $n slices, shards 0:$half and $half:$n"
# The same question asked of plain workloads first (compute, fresh memory, memory reads): a step
# that loses more than these at once loses it in its own work, not in the machine.
if [[ -x $bin/machine_bench ]]; then
  "$bin/machine_bench" | sed 's/^/machine_bench: /'
else
  echo "machine_bench: not built in $bin (tests/bench); the machine's own ceiling not measured"
fi
step register-measure "$bin/vispack-register" --config "$d/config.json" --records-only
# The solve and the QC overlays once (a chain's slices step does them per shard, ~2 s), then
# the streaming pass of the slices step: mask + labels + the pack's slabs.
"$bin/vispack-register" --config "$d/config.json" --threads 2 --quiet
step "mask + labels + pack slabs" "$bin/vispack-run" "$d/config.json" --from mask --to pack
"$bin/vispack-merge" --config "$d/config.json" --threads 2 --quiet
step vdb "$bin/vispack-vdb" --config "$d/config.json"
