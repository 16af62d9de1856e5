#!/bin/bash
# The viewer on long files (docs/BENCHMARKS.md, 'Viewer on long files'): for each stack, the
# first picture after open, a colour frame after load and a 36-frame orbit with the brick cache's
# memory against its budget (viewer_bench --orbit), with the brick tree built coarse first (now)
# and eagerly (as before: --eager-tree), and vispack-view --screenshot --timings (its breakdown of
# the first frame) of this build and, optionally, of a baseline build.
#
# usage: scripts/bench/viewer_long.sh OUT_DIR [--before BASELINE_VISPACK_VIEW]
#   Writes the synthetic stacks it lacks into OUT_DIR (viewer_bench --stack, streamed: memory one
#   brick row): 2048x1216x128, 2048x1216x1871 (the male's length) and 4368x2912x64 (the
#   Visible Korean's slice size), about 0.9 GB in all; then OUT_DIR/<stack>.{now,eager}.json and
#   the printed tables, one block per stack. Not part of scripts/test.sh.
# Env: BUILD (default build), STACKS (default "2048,1216,128 2048,1216,1871 4368,2912,64").
set -euo pipefail
here=$(cd "$(dirname "$0")/../.." && pwd)
build=${BUILD:-$here/build}
out=${1:?usage: viewer_long.sh OUT_DIR [--before BASELINE_VISPACK_VIEW]}
shift
before=""
if [ "${1:-}" = "--before" ]; then before=${2:?--before needs a vispack-view binary}; fi
bench=$build/bin/viewer_bench
view=$build/bin/vispack-view
for b in "$bench" "$view"; do
  [ -x "$b" ] || { echo "viewer_long: $b is missing (build the viewer first)" >&2; exit 1; }
done
mkdir -p "$out"
stacks=${STACKS:-"2048,1216,128 2048,1216,1871 4368,2912,64"}
# About 0.57 MB per 2048x1216 slice as written; ask for twice the total of what is missing.
need_mb=0
for s in $stacks; do
  IFS=, read -r x y z <<<"$s"
  [ -f "$out/stack_${x}x${y}x${z}.vpk" ] || need_mb=$((need_mb + 2 * x * y * z / 2048 / 1216 * 57 / 100 + 64))
done
free_mb=$(df -Pm "$out" | awk 'NR == 2 {print $4}')
if [ "$free_mb" -lt "$need_mb" ]; then
  echo "viewer_long: $out has $free_mb MB free, the stacks need about $need_mb MB" >&2
  exit 1
fi
machine() { echo "date $(date -u '+%Y-%m-%d %H:%M:%S UTC'), load average $(cut -d' ' -f1-3 /proc/loadavg)"; }
echo "commit $(git -C "$here" rev-parse --short HEAD)$(git -C "$here" diff --quiet HEAD || echo ' (with changes)'), $(nproc) cores"
for s in $stacks; do
  IFS=, read -r x y z <<<"$s"
  f=$out/stack_${x}x${y}x${z}.vpk
  [ -f "$f" ] || "$bench" --stack "$s" --keep "$f"
  echo
  echo "## $f"
  # Warm the page cache alike for both: one read of the file.
  cat "$f" >/dev/null
  machine
  "$bench" --orbit --file "$f" --json "$out/stack_${x}x${y}x${z}.now.json"
  machine
  "$bench" --orbit --file "$f" --eager-tree --json "$out/stack_${x}x${y}x${z}.eager.json"
  machine
  echo "vispack-view --screenshot --timings (this build):"
  "$view" "$f" --screenshot "$out/view.png" --timings 2>&1 | grep -E 'first frame|brick tree|^frame'
  if [ -n "$before" ]; then
    machine
    echo "vispack-view --screenshot --timings (baseline $before):"
    "$before" "$f" --screenshot "$out/view_before.png" --timings 2>&1 | grep -E 'first frame|^frame'
    cmp -s "$out/view.png" "$out/view_before.png" && echo "screenshots identical" ||
      echo "screenshots DIFFER"
  fi
done
