#!/usr/bin/env bash
# The cluster path against a real SLURM: starts a one-node cluster bound to 127.0.0.1 (munged
# with its own key and socket, slurmctld, slurmd; no systemd, no accounting) in a temporary
# folder, runs the tiny phantom through
#   1. vispack-run (local, one process: the reference),
#   2. scripts/vispack-slurm (sbatch arrays chained with afterok),
#   3. Snakemake locally (workflow/Snakefile, --cores 2),
#   4. Snakemake on the cluster (--slurm),
# and compares each packed file with the reference byte for byte. Every daemon it started is
# stopped by its PID when the script exits (trap on EXIT), whatever happened.
#
# Usage: tests/cluster/slurm_test.sh BIN_DIR   (BIN_DIR holds the vispack executables)
# Exit: 0 pass, 1 fail, 77 skipped (not root: SLURM daemons and munged need root here; or the
# Debian packages cannot be installed). Prints the time of each path (docs/BENCHMARKS.md).
# VISPACK_KEEP_TEST_DIRS=1 keeps the temporary folder (logs, job scripts, outputs).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
bin=$(cd "${1:?usage: slurm_test.sh BIN_DIR}" && pwd)
shards=${VISPACK_CLUSTER_SHARDS:-3}

skip() { echo "SKIP: $*"; exit 77; }
fail() { echo "FAIL: $*"; failed=1; }
[[ $(id -u) -eq 0 ]] || skip "the cluster test starts munged, slurmctld and slurmd, which needs root; run it as root (scripts/test.sh does)"
for tool in munged slurmctld slurmd sbatch snakemake; do
  if ! command -v "$tool" >/dev/null; then
    "$root/scripts/install-deps.sh" >/dev/null || skip "cannot install slurm-wlm, munge and snakemake (scripts/install-deps.sh failed)"
    break
  fi
done

tmp=$(mktemp -d "${TMPDIR:-/tmp}/vispack-slurm-XXXXXX")
# shellcheck source=one_node_slurm.sh
source "$root/tests/cluster/one_node_slurm.sh"
cleanup() {
  local status=$?
  [[ $status -ne 0 && $status -ne 77 ]] && ONE_NODE_SLURM_SHOW_LOGS=1
  stop_one_node_slurm
  if [[ -n ${VISPACK_KEEP_TEST_DIRS:-} ]]; then echo "kept $tmp"; else rm -rf "$tmp"; fi
}
trap cleanup EXIT
failed=0
now() { date +%s.%N; }
elapsed() { awk -v a="$1" -v b="$(now)" 'BEGIN { printf "%.1f", b - a }'; }
t=$(now)
start_one_node_slurm "$tmp/cluster" || { echo "FAIL: no cluster"; exit 1; }
echo "time: cluster start: $(elapsed "$t") s"

# ---- the phantom, four copies (each path has its own work folder) ----
"$bin/vispack-phantom" --out "$tmp/phantom" --preset tiny --seed 5 --quiet >/dev/null
# Brick edge 8: the 24 slices make 3 level-0 slabs, so the pack shards and merge really work.
sed -i 's/"brick_edge": *[0-9]*/"brick_edge": 8/' "$tmp/phantom/config.json"
grep -q '"brick_edge": 8' "$tmp/phantom/config.json" || { echo "FAIL: could not set brick_edge"; exit 1; }
for copy in local slurm snake-local snake-slurm; do cp -a "$tmp/phantom" "$tmp/$copy"; done
output=out/volume.vpk
grep -q "\"output\": \"$output\"" "$tmp/phantom/config.json" || output=$(sed -n 's/.*"output": *"\([^"]*\)".*/\1/p' "$tmp/phantom/config.json")

compare() {  # compare NAME: its packed file against the local one, byte for byte
  if [[ ! -f $tmp/$1/$output ]]; then
    fail "$1: no packed file $tmp/$1/$output"
  elif cmp "$tmp/local/$output" "$tmp/$1/$output"; then
    echo "PASS: $1 packed file is byte-identical to the local run ($(stat -c %s "$tmp/$1/$output") bytes)"
  else
    fail "$1 packed file differs from the local run"
  fi
}

# 1. Local reference (one process, one thread: the per-job work of the cluster paths).
t=$(now)
"$bin/vispack-run" "$tmp/local/config.json" --quiet --threads 1 >/dev/null
echo "time: local vispack-run --threads 1: $(elapsed "$t") s"

# 2. vispack-slurm: sbatch arrays, afterok chain, waits for the last job.
t=$(now)
if "$root/scripts/vispack-slurm" "$tmp/slurm/config.json" --shards "$shards" --bin "$bin" \
     --jobs-dir "$tmp/slurm/jobs" --partition vispack --wait >"$tmp/slurm.out" 2>&1; then
  echo "time: vispack-slurm, $shards shards: $(elapsed "$t") s ($(ls "$tmp"/slurm/jobs/*.sh | wc -l) jobs)"
  compare slurm
  # A failed shard is resubmitted alone: mask shard 1 loses an output; only that array task of the
  # per-slice job runs again, and only the lost slice is recomputed (the stages' resume: its
  # register and labels steps find everything up to date).
  rm "$tmp/slurm/work/mask/mask_0010.png"
  n=$("$bin/vispack-run" "$tmp/slurm/config.json" --plan | sed -n 's/^slices //p')
  a=$((1 * n / shards)) b=$((2 * n / shards))
  sbatch --wait --array=1 --kill-on-invalid-dep=yes "$tmp/slurm/jobs/02-slices.sh" >/dev/null ||
    fail "resubmitted per-slice task 1 failed"
  processed=$(grep -o '"processed": *[0-9]*' "$tmp/slurm/work/mask/report-$a-$b.json" | grep -o '[0-9]*$')
  if [[ -f $tmp/slurm/work/mask/mask_0010.png && $processed == 1 ]]; then
    echo "PASS: per-slice array task 1 resubmitted alone recomputed its one lost mask"
  else
    fail "resubmitted per-slice task 1: mask processed '$processed' slices (expected 1)"
  fi
else
  cat "$tmp/slurm.out"
  for log in "$tmp"/slurm/jobs/logs/*; do echo "--- $log"; cat "$log"; done
  fail "vispack-slurm chain failed"
fi

# 2b. --wait reports a failed chain: a register that fails (a stand-in executable) cancels every
# later step, and vispack-slurm --wait exits 1 saying so instead of waiting for ever.
mkdir -p "$tmp/badbin"
for exe in "$bin"/vispack-*; do ln -s "$exe" "$tmp/badbin/"; done
rm "$tmp/badbin/vispack-register"
printf '#!/bin/sh\necho "vispack-register: error: failing on purpose (slurm_test.sh)" >&2\nexit 3\n' \
  >"$tmp/badbin/vispack-register"
chmod +x "$tmp/badbin/vispack-register"
cp -a "$tmp/phantom" "$tmp/bad"
status=0
"$root/scripts/vispack-slurm" "$tmp/bad/config.json" --shards 2 --bin "$tmp/badbin" \
  --jobs-dir "$tmp/bad/jobs" --wait --poll 0.5 >"$tmp/bad.out" 2>&1 || status=$?
if [[ $status == 1 ]] && grep -q "the chain failed" "$tmp/bad.out" &&
   grep -q "CANCELLED" "$tmp/bad.out"; then
  echo "PASS: --wait exits 1 when a step fails (the rest of the chain cancelled)"
else
  cat "$tmp/bad.out"
  fail "--wait on a failing chain: exit $status (expected 1, 'the chain failed', CANCELLED)"
fi

# 3. Snakemake, locally.
snake() {  # snake COPY [snakemake options...]
  local copy=$1
  shift
  (cd "$tmp/$copy" && snakemake -s "$root/workflow/Snakefile" --quiet "$@" \
     --config vispack_config="$tmp/$copy/config.json" shards="$shards" bin="$bin" threads=1) \
    >"$tmp/$copy.out" 2>&1
}
t=$(now)
if snake snake-local --cores 2; then
  echo "time: snakemake --cores 2, $shards shards: $(elapsed "$t") s"
  compare snake-local
else
  tail -n 40 "$tmp/snake-local.out"
  fail "snakemake (local) failed"
fi

# 4. Snakemake on the cluster. 7.21 asks sacct for job states; without accounting sacct fails
# and it falls back to `scontrol show jobid` (kept by MinJobAge above), so no accounting is needed.
t=$(now)
if snake snake-slurm --slurm --jobs 4 --max-status-checks-per-second 1 --latency-wait 5 \
     --default-resources slurm_partition=vispack runtime=10 mem_mb=200; then
  echo "time: snakemake --slurm, $shards shards: $(elapsed "$t") s"
  compare snake-slurm
else
  tail -n 60 "$tmp/snake-slurm.out"
  fail "snakemake --slurm failed"
fi

if ((failed)); then exit 1; fi
echo "PASS: the SLURM and Snakemake paths give the local run's packed file, byte for byte"
