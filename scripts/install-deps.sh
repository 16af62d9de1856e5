#!/usr/bin/env bash
# Installs every Debian package that vispack's build, tests, demo and benchmarks need.
# Idempotent and non-interactive: when everything is present it only runs dpkg-query and exits.
# Usage: scripts/install-deps.sh [--bench] [--no-js]
#   --bench adds the peers the benchmark report measures; --no-js leaves the tests' npm packages
#   (scripts/fetch-js-deps.sh) to the caller (scripts/test.sh fetches them beside the build).
set -euo pipefail
bench=0 js=1
for arg in "$@"; do
  case "$arg" in
    --bench) bench=1 ;;
    --no-js) js=0 ;;
    *) echo "install-deps: unknown option $arg" >&2; exit 2 ;;
  esac
done

packages=(
  # toolchain
  build-essential cmake ninja-build pkg-config git clang libclang-rt-14-dev clang-format
  # LLVM's linker: links every executable several times faster than GNU ld (CMakeLists.txt)
  lld
  # libraries the code links
  libopencv-dev libopenimageio-dev libopenvdb-dev libboost-iostreams-dev libtbb-dev
  libzstd-dev nlohmann-json3-dev libxxhash-dev libdeflate-dev libglfw3-dev libepoxy-dev libegl-dev libgl-dev
  libimgui-dev
  # tests: GoogleTest, Google Benchmark, headless GL, reference tools
  libgtest-dev libgmock-dev libbenchmark-dev xvfb xauth libgl1-mesa-dri libegl-mesa0
  openimageio-tools libopenvdb-tools zstd
  # the Python package (python/vispack): numpy, zstandard; xxhash (fast checksums), dask (tests)
  python3-numpy python3-zstandard python3-xxhash python3-dask
  # readers of the OME-Zarr export vispack did not write (tests/python/test_ome_zarr.py):
  # zarr-python for NGFF 0.4; node + npm for zarrita (NGFF 0.5, scripts/fetch-js-deps.sh)
  python3-zarr nodejs
  # the export in a browser (tests/python/test_ome_zarr_browser.py): headless chromium with its
  # software WebGL (SwiftShader), driven by puppeteer-core (npm); screenshots read with Pillow
  chromium python3-pil
  # sample data fetch
  dpkg-dev xz-utils
  # the cluster test (tests/cluster/slurm_test.sh): a one-node SLURM, its authentication, and
  # Snakemake as the other front end (scripts/vispack-slurm, workflow/Snakefile)
  slurm-wlm munge snakemake
)
# Debian's nodejs has no npm; a node from elsewhere (NodeSource) brings its own.
command -v npm >/dev/null || packages+=(npm)
if [[ $bench == 1 ]]; then
  packages+=(gnuplot-nox elastix python3-vtk9 hyperfine valgrind time python3-matplotlib linux-perf)
fi

missing=()
for p in "${packages[@]}"; do
  status=$(dpkg-query -W -f='${Status}' "$p" 2>/dev/null || true)
  [[ "$status" == "install ok installed" ]] || missing+=("$p")
done
# The npm packages of the tests (tests/js/package.json): after the Debian ones, every run.
fetch_js() { [[ $js == 0 ]] || "$(dirname "${BASH_SOURCE[0]}")/fetch-js-deps.sh"; }
if [[ ${#missing[@]} -eq 0 ]]; then
  echo "install-deps: all ${#packages[@]} packages present"
  fetch_js
  exit 0
fi

echo "install-deps: installing ${missing[*]}"
SUDO=""
if [[ $(id -u) -ne 0 ]]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
echo "install-deps: done"
fetch_js
