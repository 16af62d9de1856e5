#!/usr/bin/env bash
# Installs the JavaScript packages the tests use (tests/js/package.json, pinned by its
# package-lock.json) into tests/js/node_modules, and bundles neuroglancer from them into
# tests/js/neuroglancer (tests/js/build_neuroglancer.mjs; both folders ignored by git):
#   zarrita        reads vispack's NGFF 0.5 (Zarr v3) export in tests/python/test_ome_zarr.py
#   neuroglancer   ES modules only on npm, bundled here by esbuild into a static viewer
#   puppeteer-core drives Debian's chromium (no browser download) in
#                  tests/python/test_ome_zarr_browser.py
# Needs node and npm (scripts/install-deps.sh) and the npm registry. Idempotent: does nothing
# when the installed tree matches the lock file and the bundle matches its build script.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
dir=$root/tests/js
command -v npm >/dev/null || { echo "fetch-js-deps: npm not found (scripts/install-deps.sh)" >&2; exit 1; }
stamp=$dir/node_modules/.vispack-lock-sha256
want=$(sha256sum "$dir/package-lock.json" | cut -d' ' -f1)
if [[ -f $stamp && $(<"$stamp") == "$want" ]]; then
  echo "fetch-js-deps: tests/js/node_modules is up to date"
else
  npm ci --prefix "$dir" --no-audit --no-fund --loglevel=error
  echo "$want" >"$stamp"
  echo "fetch-js-deps: installed $(ls "$dir/node_modules" | wc -l) packages in tests/js/node_modules"
fi
bundle_stamp=$dir/neuroglancer/.vispack-build-sha256
bundle_want=$(cat "$dir/package-lock.json" "$dir/build_neuroglancer.mjs" | sha256sum)
bundle_want=${bundle_want%% *}
if [[ -f $bundle_stamp && $(<"$bundle_stamp") == "$bundle_want" ]]; then
  echo "fetch-js-deps: tests/js/neuroglancer is up to date"
  exit 0
fi
node "$dir/build_neuroglancer.mjs" "$dir/neuroglancer"
echo "$bundle_want" >"$bundle_stamp"
