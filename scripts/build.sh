#!/usr/bin/env bash
# Configures and builds vispack. Usage: scripts/build.sh [BUILD_DIR] [extra cmake -D options...]
# Default BUILD_DIR is build/ (Release). Executables land in BUILD_DIR/bin.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
build_dir=${1:-$root/build}
shift || true
build_type=${VISPACK_BUILD_TYPE:-Release}
# The configure log lives inside the build folder (ignored by git), never beside it.
mkdir -p "$build_dir"
log="$build_dir/configure.log"
cmake -S "$root" -B "$build_dir" -G Ninja -DCMAKE_BUILD_TYPE="$build_type" "$@" >"$log" 2>&1 || {
  cat "$log"; echo "build: cmake configure failed (log above)" >&2; exit 1; }
cmake --build "$build_dir" -j "${VISPACK_JOBS:-$(nproc)}"
