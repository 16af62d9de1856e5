#!/usr/bin/env bash
# Packs built executables with the shared libraries they load into one folder, for a machine that
# has none of the project's packages and cannot install them (a lent GPU machine with no package
# archive: docs/BENCHMARKS.md "On a GPU machine with 16 cores"). Build with
# -DVISPACK_WITH_OPENIMAGEIO=OFF first: OpenImageIO alone loads ~260 libraries (345 MB); without
# it the bundle is a few tens of MB.
#   DEST/bin/   the executables (every vispack-* of BIN_DIR, the benchmarks named below when
#               built, and this machine's zstd for the encoder's peer)
#   DEST/lib/   every library they load, found by ldd, except the C and C++ runtimes (libc, libm,
#               libstdc++, libgcc_s, the loader) and the GL dispatch libraries (libEGL, libGL,
#               libOpenGL, libGLX, libGLdispatch): the target machine's own are used, so it needs
#               a glibc and libstdc++ at least as new as this machine's, and its GL vendor's EGL
#   DEST/scripts/  the scripts the benchmark runs there (cluster_plan.py, bench/local_chain.py,
#               bench/big_machine.sh)
# Run a bundled program with LD_LIBRARY_PATH=DEST/lib. Exits 1 when a library cannot be found.
# Usage: scripts/bench/bundle.sh BIN_DIR DEST
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
bin=$(cd "${1:?usage: bundle.sh BIN_DIR DEST}" && pwd)
dest=${2:?usage: bundle.sh BIN_DIR DEST}
rm -rf "$dest"
mkdir -p "$dest/bin" "$dest/lib" "$dest/scripts/bench"
programs=("$bin"/vispack-*)
for bench in viewer_bench machine_bench format_writer_raw_bench; do
  [[ -x $bin/$bench ]] && programs+=("$bin/$bench")
done
programs+=("$(command -v zstd)")
cp "${programs[@]}" "$dest/bin/"
skip='^(libc|libm|libdl|libpthread|librt|libutil|libresolv|ld-linux-x86-64|libstdc\+\+|libgcc_s|libEGL|libGL|libGLX|libGLdispatch|libOpenGL|libGLESv2)\.so'
for program in "${programs[@]}"; do
  if ldd "$program" | grep -q 'not found'; then
    ldd "$program" | grep 'not found' >&2
    echo "bundle.sh: $program: a library is missing on this machine" >&2
    exit 1
  fi
  ldd "$program" | awk '$2 == "=>" && $3 ~ /^\// { print $1, $3 }'
done | sort -u | while read -r soname path; do
  [[ $soname =~ $skip ]] || cp -L "$path" "$dest/lib/$soname"
done
# Every library a bundled program loads (with LD_LIBRARY_PATH=DEST/lib) is the bundle's own, or
# one of the runtimes left to the target machine.
dest_lib=$(cd "$dest/lib" && pwd)
for program in "$dest"/bin/*; do
  LD_LIBRARY_PATH=$dest_lib ldd "$program" | awk '$2 == "=>" { print $1, $3 }' |
    while read -r soname path; do
      [[ $soname =~ $skip || $path == "$dest_lib/"* ]] ||
        { echo "bundle.sh: $program loads $soname from $path, outside the bundle" >&2; exit 1; }
    done || exit 1
done
cp "$root/scripts/cluster_plan.py" "$dest/scripts/"
cp "$root/scripts/bench/local_chain.py" "$root/scripts/bench/big_machine.sh" "$dest/scripts/bench/"
echo "bundle: $(ls "$dest/bin" | wc -l) programs, $(ls "$dest/lib" | wc -l) libraries, $(du -sh "$dest" | cut -f1)"
