#!/usr/bin/env bash
# Installs the JavaScript packages the tests use (tests/js/package.json, pinned by its
# package-lock.json) into tests/js/node_modules (ignored by git): zarrita, which reads vispack's
# NGFF 0.5 (Zarr v3) export in tests/python/test_ome_zarr.py. Needs node and npm (Debian's
# nodejs and npm, scripts/install-deps.sh) and the npm registry. Idempotent: does nothing when
# the installed tree matches the lock file.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
dir=$root/tests/js
command -v npm >/dev/null || { echo "fetch-js-deps: npm not found (scripts/install-deps.sh)" >&2; exit 1; }
stamp=$dir/node_modules/.vispack-lock-sha256
want=$(sha256sum "$dir/package-lock.json" | cut -d' ' -f1)
if [[ -f $stamp && $(<"$stamp") == "$want" ]]; then
  echo "fetch-js-deps: tests/js/node_modules is up to date"
  exit 0
fi
npm ci --prefix "$dir" --no-audit --no-fund --loglevel=error
echo "$want" >"$stamp"
echo "fetch-js-deps: installed $(ls "$dir/node_modules" | tr '\n' ' ')"
