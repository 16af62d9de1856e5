#!/usr/bin/env bash
# Runs the whole test suite: installs what is missing, fetches the tests' npm packages and the
# real sample data (beside the next two steps), checks the C++ formatting
# (scripts/check-format.sh), builds Release,
# runs ctest (unit, command-line and headless image tests), the cluster tests (a one-node SLURM,
# tests/cluster/; they skip where not root; they run beside the sanitizer build, since they mostly
# wait), then the sanitizer build (ASan+UBSan) of every test but the benchmarks, short fuzz runs
# (the targets side by side, one per core) and the quick benchmark. Both builds use
# -Werror (VISPACK_WERROR). Prints each step's time and the total.
# Usage: scripts/test.sh [--sanitize-only] [--no-sanitize] [--no-fuzz] [--no-bench]
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
sanitize=1 fuzz=1 bench=1 main=1
for arg in "$@"; do
  case "$arg" in
    --sanitize|--sanitize-only) main=0 ;;
    --no-sanitize) sanitize=0 ;;
    --no-fuzz) fuzz=0 ;;
    --no-bench) bench=0 ;;
    -h|--help) sed -n '2,10p' "$0"; exit 0 ;;
    *) echo "test.sh: unknown option $arg" >&2; exit 2 ;;
  esac
done
jobs=${VISPACK_JOBS:-$(nproc)}
start=$(date +%s)
# Each step is announced with the time since the start; when the next one begins (or the script
# ends, even on an error) its duration is printed, and the end prints every step's time and the
# total.
step_names=() step_seconds=() step_name="" step_start=$start
end_step() {
  [[ -n $step_name ]] || return 0
  local seconds=$(( $(date +%s) - step_start ))
  printf '== %s: %ds\n' "$step_name" "$seconds"
  step_names+=("$step_name") step_seconds+=("$seconds") step_name=""
}
stamp() {
  end_step
  step_name="$*" step_start=$(date +%s)
  printf '\n== [%4ds] %s\n' $(( step_start - start )) "$*"
}
summary() {
  # A step that failed under `set -e` ends the script: the cluster tests still running beside the
  # sanitizer build are waited for, so their result is not lost.
  if [[ -n ${cluster_pid:-} ]]; then
    wait "$cluster_pid" || echo "test.sh: the cluster tests failed (output below)" >&2
    cat "$cluster_log"
  fi
  if [[ -n ${fetch_js_pid:-} ]]; then
    wait_for_fetches || true
  fi
  end_step
  echo
  echo "== Time per step"
  local i
  for i in "${!step_names[@]}"; do
    printf '%6ds  %s\n' "${step_seconds[$i]}" "${step_names[$i]}"
  done
  printf '%6ds  total\n' $(( $(date +%s) - start ))
}
trap summary EXIT

stamp "Installing missing Debian packages"
scripts/install-deps.sh --no-js

failed=0 cluster_pid="" cluster_log="" fetch_js_pid="" fetch_samples_pid=""
# Under CI (CI=true, as .ci/run sees it) or with VISPACK_STRICT=1 a skipped test fails the run:
# a suite that skips what it cannot check is green while checking nothing. The tests that may
# skip even there are listed in tests/optional_skips.txt (a ctest name regex and the reason per
# line; the README names them).
strict=0
[[ ${CI:-} == true || ${VISPACK_STRICT:-0} == 1 ]] && strict=1
# The tests' npm packages and the real sample data are downloads and unpacking (about 20 s on a
# fresh clone, little CPU): they run beside the formatting check and the release build, and the
# first ctest waits for them (wait_for_fetches), which prints their output then.
stamp "Fetching the tests' npm packages and the real sample data (beside the build)"
fetch_js_log=$(mktemp) fetch_samples_log=$(mktemp)
scripts/fetch-js-deps.sh >"$fetch_js_log" 2>&1 &
fetch_js_pid=$!
scripts/fetch-sample-data.sh >"$fetch_samples_log" 2>&1 &
fetch_samples_pid=$!
wait_for_fetches() {
  [[ -n $fetch_js_pid ]] || return 0
  if ! wait "$fetch_js_pid"; then
    echo "test.sh: fetching the tests' npm packages failed (output below)" >&2
    failed=1
  fi
  cat "$fetch_js_log"
  if ! wait "$fetch_samples_pid"; then
    if [[ $strict == 1 ]]; then
      echo "test.sh: the sample data fetch failed: under CI every real-data test must run" >&2
      failed=1
    else
      echo "test.sh: warning: sample data fetch failed; data tests will skip"
    fi
  fi
  cat "$fetch_samples_log"
  rm -f "$fetch_js_log" "$fetch_samples_log"
  fetch_js_pid="" fetch_samples_pid=""
}

# run_ctest DIR ARGS...: ctest in DIR (no test matching is an error); under strict, a test that
# did not run (skipped or disabled) and is not in tests/optional_skips.txt is a failure.
run_ctest() {
  local dir=$1 log rc=0
  shift
  log=$(mktemp)
  (cd "$dir" && ctest --output-on-failure --no-tests=error "$@") 2>&1 | tee "$log" || rc=1
  if [[ $strict == 1 ]]; then
    local not_run
    not_run=$(sed -n '/^The following tests did not run:/,/^$/p' "$log" | grep -E '^\s+[0-9]+ - ' |
      sed -E 's/^\s+[0-9]+ - //' || true)
    if [[ -n $not_run ]]; then
      local allowed
      allowed=$(grep -v '^\s*#' tests/optional_skips.txt | cut -f1 | grep -v '^\s*$' | paste -sd'|' || true)
      local bad
      bad=$(grep -vE "^(${allowed:-^$})( |$)" <<<"$not_run" || true)
      if [[ -n $bad ]]; then
        echo "test.sh: under CI these tests did not run, and tests/optional_skips.txt does not allow it:" >&2
        sed 's/^/  /' <<<"$bad" >&2
        rc=1
      fi
    fi
  fi
  rm -f "$log"
  return $rc
}
stamp "Checking the C++ formatting (scripts/check-format.sh)"
scripts/check-format.sh || failed=1

if [[ $main == 1 ]]; then
  stamp "Building (Release) into build/"
  scripts/build.sh "$root/build" -DVISPACK_WERROR=ON
  stamp "Waiting for the npm packages and the sample data (fetched beside the build)"
  wait_for_fetches
  stamp "Running ctest (all but the cluster tests)"
  run_ctest build -j "$jobs" --timeout 600 -LE cluster || failed=1
  # Apart from the rest: the real-SLURM test starts daemons and times the cluster paths
  # (tests/cluster/). They spend most of their minute waiting on SLURM and Snakemake, so when the
  # sanitizer build follows they run beside it, their output printed when they end.
  if [[ $sanitize == 1 ]]; then
    cluster_log=$root/build/cluster-tests.log
    echo "test.sh: the cluster tests run beside the sanitizer build (output: $cluster_log)"
    run_ctest build --timeout 600 -L cluster >"$cluster_log" 2>&1 &
    cluster_pid=$!
  else
    stamp "Cluster tests: one-node SLURM and Snakemake against vispack-run (ctest -L cluster)"
    run_ctest build --timeout 600 -L cluster || failed=1
  fi
fi

if [[ $sanitize == 1 ]]; then
  # One clang build serves both the sanitized tests and the fuzzers (scripts/fuzz.sh).
  # Everything but the benchmarks: the render library and the headless viewer too (EGL on Mesa
  # llvmpipe; tests/CMakeLists.txt explains the one environment setting GL tests get).
  stamp "Building with clang, ASan+UBSan and libFuzzer into build-sanitize/"
  CC=clang CXX=clang++ VISPACK_BUILD_TYPE=RelWithDebInfo scripts/build.sh "$root/build-sanitize" \
    -DVISPACK_SANITIZE=ON -DVISPACK_FUZZ=ON -DVISPACK_BUILD_BENCH=OFF -DVISPACK_WERROR=ON
  if [[ -n $cluster_pid ]]; then
    stamp "Cluster tests (ran beside the sanitizer build): one-node SLURM and Snakemake against vispack-run"
    wait "$cluster_pid" || failed=1
    cluster_pid=""
    cat "$cluster_log"
  fi
  if [[ -n $fetch_js_pid ]]; then
    stamp "Waiting for the npm packages and the sample data (fetched beside the build)"
    wait_for_fetches
  fi
  # Leak detection on (our code is checked for leaks), every UBSan finding fatal.
  stamp "Running sanitized tests (common, format, pipeline, render, viewer, data, cli, phantom, python)"
  # Nine accuracy cases on real data, at the real slice size, or running again at full cost what
  # a sibling case runs take a third of the sanitized run's CPU time (about 630 of 1,630 s; ASan
  # slows them 3-4x) and run no code that a smaller or sibling case of the same test program does
  # not run under the sanitizers (the phantom's 3:1 z-spacing case runs the 5:1 case's code with
  # another ratio; the gap in the colour numbers runs the missing letter's pipeline, the letter
  # names themselves are SliceZ.LetterSuffixPatternOrdersTheFemalesFiles and
  # SliceZ.ColourSlicesArePlacedByTheirFileNumber; BodyParts.MalePresetAgainstTruth,
  # Bricks.LabelShadingAndTf2dMatchTheReference, the viewer's other Defaults cases): the release
  # run has them all (README "Running the tests").
  sanitize_skip='^(RegisterStage\.AnatomyVhpPresetAtRealSize|RegisterStage\.HeadCtCaseAgainstTruth|Defaults\.NoWoodGrainAtTheDefaultDensity|Defaults\.Tf2dShowsTheBoundariesOfTheTissues|SliceZ\.HeadCtCaseWithColour(Three|Five)TimesFinerThanTheCt|SliceZ\.PhantomWithCtAtEveryFifthColourSliceMeetsTheGoals|SliceZ\.AMissingLetterLeavesTheLaterSlicesInPlace|BodyParts\.RealBrainSlicesWithSeveralParts)$'
  ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
    run_ctest build-sanitize -j "$jobs" --timeout 900 -L 'common|format|pipeline|render|viewer|data|cli|phantom|python' \
    -E "$sanitize_skip" ||
    failed=1
fi

if [[ $fuzz == 1 && $sanitize == 1 && -x scripts/fuzz.sh ]]; then
  stamp "Short fuzz runs"
  scripts/fuzz.sh --seconds "${VISPACK_FUZZ_SECONDS:-20}" --build "$root/build-sanitize" || failed=1
fi

if [[ $bench == 1 && -x scripts/bench.sh ]]; then
  stamp "Quick benchmark (keeps the benchmarks from rotting)"
  scripts/bench.sh --quick --no-report || failed=1
fi

if [[ $failed != 0 ]]; then
  echo "test.sh: FAILED (see above)" >&2
  exit 1
fi
echo "test.sh: all test steps passed"
