#!/usr/bin/env bash
# The whole male at full length (docs/BENCHMARKS.md 'The whole male at full length'): generates
# male-shaped stacks of 128, 512 and 1,871 distinct 2048x1216 slices as NLM ships them, a
# female-shaped one (1,500 colour slices, a CT slice at every third) and a Visible-Korean-sized
# one (4368x2912), runs `vispack-run CONFIG --threads 2` on each with a cold
# and a warm page cache, scores it, deletes the stacks, and (with --report) writes the section
# into docs/BENCHMARKS.md and docs/img/full_length.png. Its own entry point: scripts/test.sh and
# a plain scripts/bench.sh do not run it (scripts/bench.sh --full-length does). About 75 minutes
# of two cores and 25 GB of disk at the default lengths (each stack is deleted after its runs); run as root for the cold page cache.
# Usage: scripts/bench/full_length.sh [--build DIR] [--no-build] [--slices "128 512 1871"]
#          [--korean N] [--female N] [--work DIR] [--keep-free-gb GB] [--keep-stacks] [--warm-first] [--report]
#          [--require-clean] [--generator BIN] [--generate-only] [--no-cold]
#   --slices     male stack lengths (default "128 512 1871")
#   --korean N   slices of the Korean-sized stack (default 64; 0: none)
#   --female N   colour slices of the female-shaped stack: the male body with a CT slice at every
#                third colour slice, as the VH female's (default 1500; 0: none)
#   --work DIR   where the stacks are generated (default BUILD/bench/full_length/stacks); a stack
#                made by the same generator with the same arguments is reused
#   --keep-free-gb GB  stop with a message before (or kill a run when) the free space of the work
#                folder would fall under GB (default 10)
#   --keep-stacks  keep the generated stacks (default: each deleted after its runs)
#   --warm-first the warm run first, then the cold one (default: cold, then warm)
#   --report     write the section into docs/BENCHMARKS.md and the plot into docs/img
#   --require-clean  refuse to run from a tree that differs from its commit
#   --generator BIN  the vispack-phantom that makes the stacks (default: the build's; a copy kept
#                aside lets stacks made once be reused by the runs of later commits)
#   --generate-only  make (or find) the stacks and stop: no runs, no report, the stacks kept
#   --no-cold    the warm run only (no page-cache drop, which needs root)
# Results: BUILD/bench/full_length/results/full_length.json and the logs beside it.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
build=${VISPACK_BENCH_BUILD:-$root/build} do_build=1 report=0 require_clean=0 work=""
slices="128 512 1871" korean=64 female=1500 keep_free=10 keep_stacks=() order=() generator=() generate_only=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --build) build=$(realpath -m "$2"); shift ;;
    --no-build) do_build=0 ;;
    --slices) slices=$2; shift ;;
    --korean) korean=$2; shift ;;
    --female) female=$2; shift ;;
    --work) work=$(realpath -m "$2"); shift ;;
    --keep-free-gb) keep_free=$2; shift ;;
    --keep-stacks) keep_stacks=(--keep-stacks) ;;
    --warm-first) order=(--warm-first) ;;
    --report) report=1 ;;
    --require-clean) require_clean=1 ;;
    --generator) generator=(--generator "$(realpath -m "$2")"); shift ;;
    --generate-only) generate_only=(--generate-only) ;;
    --no-cold) order+=(--no-cold) ;;
    -h|--help) sed -n '2,25p' "$0"; exit 0 ;;
    *) echo "full_length.sh: unknown option $1" >&2; exit 2 ;;
  esac
  shift
done
py=/usr/bin/python3
fail() { echo "full_length.sh: $*" >&2; exit 1; }
[[ -x $py ]] || fail "$py is missing"
[[ $report == 0 ]] || "$py" -c 'import matplotlib' 2>/dev/null ||
  fail "python3-matplotlib is missing (scripts/install-deps.sh --bench)"
[[ -x /usr/bin/time ]] || fail "/usr/bin/time is missing (apt-get install time)"
if [[ $require_clean == 1 ]]; then
  dirty=$("$py" -c 'import sys; sys.path.insert(0, sys.argv[1]); import machine
print(int(machine.provenance()["dirty"]))' "$root/scripts/bench")
  [[ $dirty == 0 ]] || fail "--require-clean: the tree differs from its commit (git status)"
fi
if [[ $do_build == 1 ]]; then
  [[ -f $build/CMakeCache.txt ]] || VISPACK_BUILD_TYPE=Release "$root/scripts/build.sh" "$build"
  cmake --build "$build" -j "${VISPACK_JOBS:-$(nproc)}" --target vispack-phantom vispack-run \
    vispack-score >"$build/full-length-build.log" 2>&1 || {
    tail -30 "$build/full-length-build.log"; fail "build failed (log: $build/full-length-build.log)"; }
fi
out=$build/bench/full_length
res=$out/results
work=${work:-$out/stacks}
mkdir -p "$res" "$work"
"$py" "$root/scripts/bench/machine.py" >"$res/machine.json"
status=0
"$py" "$root/scripts/bench/full_length.py" --bin "$build/bin" --work "$work" --results "$res" \
  --slices "$slices" --korean "$korean" --female "$female" --keep-free-gb "$keep_free" "${keep_stacks[@]}" "${order[@]}" \
  "${generator[@]}" "${generate_only[@]}" || status=$?
if [[ $report == 1 && ${#generate_only[@]} == 0 && -f $res/full_length.json ]]; then
  "$py" "$root/scripts/bench/full_length_report.py" "$res" "$root/docs"
fi
exit $status
