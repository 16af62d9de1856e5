#!/usr/bin/env bash
# Runs every case of one GoogleTest suite in one process: the ctest test "SUITE.*" that
# tests/CMakeLists.txt registers for a suite whose SetUpTestSuite builds an input all its cases
# share. Exits with the executable's status when it fails, 77 (ctest: skipped; a failure under CI,
# scripts/test.sh) when a case skipped and none failed, so a skip never hides a failure, and 1
# when no case ran (a suite name that matches nothing).
# Usage: run_gtest_suite.sh EXECUTABLE SUITE
set -uo pipefail
if [[ $# -ne 2 ]]; then
  echo "usage: run_gtest_suite.sh EXECUTABLE SUITE" >&2
  exit 2
fi
log=$(mktemp)
trap 'rm -f "$log"' EXIT
"$1" --gtest_filter="$2.*" 2>&1 | tee "$log"
rc=${PIPESTATUS[0]}
if [[ $rc -ne 0 ]]; then
  exit "$rc"
fi
if ! grep -qE '^\[==========\] [1-9][0-9]* tests? from .* ran' "$log"; then
  echo "run_gtest_suite.sh: no case of suite $2 ran in $1" >&2
  exit 1
fi
if grep -q '^\[  SKIPPED \]' "$log"; then
  exit 77
fi
