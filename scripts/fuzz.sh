#!/usr/bin/env bash
# Runs each libFuzzer target for a while on its seed corpus (docs/RELIABILITY.md).
# Usage: scripts/fuzz.sh [--seconds N] [--build DIR] [--parallel P] [TARGET ...]
#   Builds DIR (default build-sanitize/, clang + ASan + UBSan + libFuzzer) if needed, writes each
#   target's seed corpus with <target>_replay --seeds, then runs <target> for N seconds (default 30).
#   A libFuzzer run uses one core: P targets run at once (default: the number of cores).
#   Corpus and crash files go to out/fuzz/<target>/. Exits non-zero if any target finds a crash.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
seconds=30 build=$root/build-sanitize parallel=$(nproc) targets=()
while [[ $# -gt 0 ]]; do
  case "$1" in
    --seconds) seconds=$2; shift 2 ;;
    --build) build=$2; shift 2 ;;
    --parallel) parallel=$2; shift 2 ;;
    -h|--help) sed -n '2,8p' "$0"; exit 0 ;;
    *) targets+=("$1"); shift ;;
  esac
done
if [[ ! -x $build/bin/fuzz_format_reader ]]; then
  CC=clang CXX=clang++ VISPACK_BUILD_TYPE=RelWithDebInfo "$root/scripts/build.sh" "$build" \
    -DVISPACK_SANITIZE=ON -DVISPACK_FUZZ=ON -DVISPACK_BUILD_VIEWER=OFF -DVISPACK_BUILD_BENCH=OFF
fi
if [[ ${#targets[@]} -eq 0 ]]; then
  targets=(fuzz_format_reader fuzz_config fuzz_raw_slice fuzz_png_decode)
fi
# run_target T: one fuzz run; prints its summary in one block when it ends (runs may overlap),
# and returns non-zero when it found a problem.
run_target() {
  local t=$1 dir=$root/out/fuzz/$1 rc=0
  mkdir -p "$dir/corpus" "$dir/seeds" "$dir/crashes"
  rm -f "$dir/summary.txt"
  "$build/bin/${t}_replay" --seeds "$dir/seeds" >/dev/null
  if ! ASAN_OPTIONS=detect_leaks=0:abort_on_error=1 "$build/bin/$t" "$dir/corpus" "$dir/seeds" \
      -max_total_time="$seconds" -timeout=20 -rss_limit_mb=4096 -max_len=262144 \
      -artifact_prefix="$dir/crashes/" -print_final_stats=1 >"$dir/log.txt" 2>&1; then
    rc=1
  fi
  {
    echo "fuzz: $t ran for ${seconds}s"
    if [[ $rc != 0 ]]; then
      echo "fuzz: $t FOUND A PROBLEM: see $dir/log.txt and $dir/crashes/"
      tail -30 "$dir/log.txt"
    fi
    grep -E '^stat::number_of_executed_units|^stat::peak_rss_mb' "$dir/log.txt" | sed "s/^/fuzz: $t /" || true
    # Final coverage (cov: edges, ft: features) for docs/RELIABILITY.md.
    grep -E '^#[0-9]+[[:space:]]+DONE' "$dir/log.txt" | tail -1 | sed "s/^/fuzz: $t /" || true
  } >"$dir/summary.txt"
  return $rc
}

status=0 pids=() names=()
# finish_one: waits for the oldest run still going and prints its summary.
finish_one() {
  local t=${names[0]} pid=${pids[0]}
  if ! wait "$pid"; then status=1; fi
  local summary=$root/out/fuzz/$t/summary.txt
  if [[ ! -f $summary ]]; then
    echo "fuzz: $t failed before its run ended (its seeds could not be written?)" >&2
    status=1
  elif grep -q "FOUND A PROBLEM" "$summary"; then
    cat "$summary" >&2
  else
    cat "$summary"
  fi
  pids=("${pids[@]:1}") names=("${names[@]:1}")
}
for t in "${targets[@]}"; do
  if [[ ! -x $build/bin/$t ]]; then
    # Under CI (CI=true or VISPACK_STRICT=1) a fuzz target that was not built is a failure.
    if [[ ${CI:-} == true || ${VISPACK_STRICT:-0} == 1 ]]; then
      echo "fuzz: $t was not built (under CI every fuzz target must run)" >&2
      status=1
    else
      echo "fuzz: $t not built, skipped"
    fi
    continue
  fi
  [[ ${#pids[@]} -lt $parallel ]] || finish_one
  echo "fuzz: $t for ${seconds}s"
  run_target "$t" &
  pids+=($!) names+=("$t")
done
while [[ ${#pids[@]} -gt 0 ]]; do finish_one; done
exit $status
