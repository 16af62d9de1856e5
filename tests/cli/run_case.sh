#!/usr/bin/env bash
# Golden command-line test: runs one case, tests/cli/<tool>/<case>/, and compares the exit code,
# stdout and stderr with the files of the case (exactly, after path substitution).
#
# A case folder holds
#   args       the command line after the program (bash words: quoting works; relative paths)
#   exit_code  the expected exit code
#   stdout     the expected standard output
#   stderr     the expected standard error
#   files/     optional: copied into the scratch folder the command runs in
#   setup      optional: bash run in the scratch folder first, with $BIN = the build's bin folder
#              (to make real inputs, e.g. a tiny phantom)
# The command runs in a fresh scratch folder; in its output the scratch folder's path becomes
# <d> and the bin folder's path <bin>, so the expected files hold no absolute path.
# VISPACK_UPDATE_GOLDEN=1 rewrites exit_code, stdout and stderr from the current output (review
# the diff before committing). VISPACK_KEEP_TEST_DIRS=1 keeps the scratch folder.
#
# Usage: run_case.sh BIN_DIR CASE_DIR
set -uo pipefail
bin=$(cd "$1" && pwd)
case_dir=$(cd "$2" && pwd)
tool=$(basename "$(dirname "$case_dir")")
name="$tool/$(basename "$case_dir")"

work=$(mktemp -d "${TMPDIR:-/tmp}/vispack-cli-XXXXXX")
work=$(cd "$work" && pwd -P)
scratch=$work/d  # where the command runs; its outputs are captured beside it, in $work
mkdir "$scratch"
cleanup() {
  if [[ -n ${VISPACK_KEEP_TEST_DIRS:-} ]]; then
    echo "kept $work" >&2
  else
    rm -rf "$work"
  fi
}
trap cleanup EXIT

[[ -f $case_dir/args ]] || { echo "$name: no args file" >&2; exit 1; }
[[ -x $bin/$tool ]] || { echo "$name: $bin/$tool is not built" >&2; exit 1; }
if [[ -d $case_dir/files ]]; then
  cp -R "$case_dir/files/." "$scratch/"
fi
if [[ -f $case_dir/setup ]]; then
  (cd "$scratch" && BIN=$bin bash -euo pipefail "$case_dir/setup") >"$work/setup.log" 2>&1 || {
    echo "$name: setup failed:" >&2
    cat "$work/setup.log" >&2
    exit 1
  }
fi

args=$(<"$case_dir/args")
program=$bin/$tool
(cd "$scratch" && eval "exec \"\$program\" $args") >"$work/stdout" 2>"$work/stderr" </dev/null
code=$?

# Substitute the scratch and bin folders (longest first), as plain strings.
normalise() {
  local text
  text=$(<"$1")
  text=${text//"$scratch"/<d>}
  text=${text//"$bin"/<bin>}
  printf '%s' "$text"
}
got_out=$(normalise "$work/stdout")
got_err=$(normalise "$work/stderr")

if [[ -n ${VISPACK_UPDATE_GOLDEN:-} ]]; then
  printf '%s\n' "$code" >"$case_dir/exit_code"
  if [[ -n $got_out ]]; then printf '%s\n' "$got_out" >"$case_dir/stdout"; else : >"$case_dir/stdout"; fi
  if [[ -n $got_err ]]; then printf '%s\n' "$got_err" >"$case_dir/stderr"; else : >"$case_dir/stderr"; fi
  echo "$name: golden files rewritten (exit $code)"
  exit 0
fi

failed=0
expected_code=$(tr -d '[:space:]' <"$case_dir/exit_code" 2>/dev/null)
if [[ $code != "$expected_code" ]]; then
  echo "$name: exit code $code, expected ${expected_code:-<no exit_code file>}"
  failed=1
fi
for stream in stdout stderr; do
  if [[ $stream == stdout ]]; then got=$got_out; else got=$got_err; fi
  expected=""
  [[ -f $case_dir/$stream ]] && expected=$(<"$case_dir/$stream")
  if [[ $got != "$expected" ]]; then
    echo "$name: $stream differs (--- expected, +++ got):"
    diff -u <(printf '%s\n' "$expected") <(printf '%s\n' "$got") | tail -n +3
    failed=1
  fi
done
if [[ $failed == 0 ]]; then
  echo "$name: exit $code, stdout and stderr as expected"
else
  echo "(VISPACK_UPDATE_GOLDEN=1 ctest -R '^cli\.' rewrites the expected files after a deliberate change)"
fi
exit $failed
