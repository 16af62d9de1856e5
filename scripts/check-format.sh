#!/usr/bin/env bash
# Checks that every C++ source and header of the project is formatted with the project's
# .clang-format (clang-format from Debian, scripts/install-deps.sh). Lists the files that are not
# and exits 1; --fix formats them in place instead.
# Usage: scripts/check-format.sh [--fix]
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
fix=0
case "${1:-}" in
  --fix) fix=1 ;;
  "") ;;
  -h|--help) sed -n '2,5p' "$0"; exit 0 ;;
  *) echo "check-format: unknown option $1" >&2; exit 2 ;;
esac
command -v clang-format >/dev/null || { echo "check-format: clang-format not found (scripts/install-deps.sh installs it)" >&2; exit 1; }
# The project's own sources: every folder but build outputs and fetched data (npm packages in
# tests/js/node_modules carry C++ of their own).
mapfile -t files < <(find common format pipeline phantom viewer tests -name node_modules -prune -o \
  \( -name '*.cpp' -o -name '*.h' \) -type f -print | sort)
if [[ $fix == 1 ]]; then
  clang-format -i "${files[@]}"
  echo "check-format: formatted ${#files[@]} files"
  exit 0
fi
# One clang-format per file, as many at once as there are cores; the files it rejects, sorted.
mapfile -t bad < <(printf '%s\0' "${files[@]}" | xargs -0 -P "$(nproc)" -n 16 sh -c \
  'for f; do clang-format --dry-run --Werror "$f" >/dev/null 2>&1 || echo "$f"; done' sh | sort)
if (( ${#bad[@]} )); then
  echo "check-format: ${#bad[@]} of ${#files[@]} files are not formatted (.clang-format):" >&2
  printf '  %s\n' "${bad[@]}" >&2
  echo "check-format: run scripts/check-format.sh --fix" >&2
  exit 1
fi
echo "check-format: ${#files[@]} files formatted"
