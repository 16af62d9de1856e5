#!/bin/bash
# The lean build (-DVISPACK_WITH_OPENIMAGEIO=OFF; docs/ARCHITECTURE.md "The lean build") end to
# end, against the default build: configures and builds the lean variant's vispack-run,
# vispack-phantom, vispack-view and viewer_bench, checks that none of them loads OpenImageIO
# (and prints each one's library count beside the default build's), makes a phantom with the
# lean vispack-phantom, runs both builds' vispack-run (and the lean one with --staged, which
# reads its own PNG intermediates back) on copies of it and requires the packed files to be
# byte-identical (and, where OpenImageIO's idiff is installed, every work-folder PNG
# to hold the same pixels), runs viewer_bench briefly, takes a vispack-view screenshot and reads
# it back, and checks that a JPEG output is refused naming the file.
# Not run by scripts/test.sh (a third build: minutes of CPU). Run it by hand:
#   tests/cli/lean_build.sh [DEFAULT_BUILD_DIR [LEAN_BUILD_DIR]]   (default: build, build-lean)
# VISPACK_LEAN_PRESET / VISPACK_LEAN_SLICES pick the phantom (default: vhp, 16 slices).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
default_build=$(realpath -m "${1:-$root/build}")
lean_build=$(realpath -m "${2:-$root/build-lean}")
preset=${VISPACK_LEAN_PRESET:-vhp}
slices=${VISPACK_LEAN_SLICES:-16}
tools=(vispack-run vispack-phantom vispack-view viewer_bench)
fail() { echo "lean_build: FAIL: $*" >&2; exit 1; }

[[ -x $default_build/bin/vispack-run && -x $default_build/bin/vispack-view ]] ||
  fail "$default_build/bin has no vispack-run or vispack-view: build the default build first"
if [[ ! -f $lean_build/CMakeCache.txt ]]; then
  cmake -S "$root" -B "$lean_build" -G Ninja -DCMAKE_BUILD_TYPE=Release \
    -DVISPACK_WITH_OPENIMAGEIO=OFF -DVISPACK_BUILD_BENCH=ON -DVISPACK_WERROR=ON \
    -DCMAKE_CXX_COMPILER_LAUNCHER=ccache -DCMAKE_C_COMPILER_LAUNCHER=ccache >/dev/null
fi
grep -q '^VISPACK_WITH_OPENIMAGEIO:BOOL=OFF$' "$lean_build/CMakeCache.txt" ||
  fail "$lean_build is not configured with -DVISPACK_WITH_OPENIMAGEIO=OFF"
if grep -q '^OpenImageIO_DIR:' "$lean_build/CMakeCache.txt"; then
  grep '^OpenImageIO_DIR:' "$lean_build/CMakeCache.txt" | grep -q NOTFOUND ||
    fail "$lean_build: CMake looked for OpenImageIO (OpenImageIO_DIR in the cache)"
fi
nice -n 19 cmake --build "$lean_build" --target "${tools[@]}" >/dev/null

echo "shared libraries (ldd | wc -l): lean / default"
for t in "${tools[@]}"; do
  lean_libs=$(ldd "$lean_build/bin/$t")
  ! grep -qi openimageio <<<"$lean_libs" || fail "lean $t loads OpenImageIO"
  ! readelf -d "$lean_build/bin/$t" | grep -qi openimageio || fail "lean $t needs OpenImageIO"
  default_count=-
  [[ -x $default_build/bin/$t ]] && default_count=$(ldd "$default_build/bin/$t" | wc -l)
  echo "  $t: $(wc -l <<<"$lean_libs") / $default_count"
done

tmp=$(mktemp -d "${TMPDIR:-/tmp}/vispack-lean-XXXXXX")
trap 'rm -rf "$tmp"' EXIT
"$lean_build/bin/vispack-phantom" --out "$tmp/phantom" --preset "$preset" --slices "$slices" \
  --quiet >/dev/null
cp -r "$tmp/phantom" "$tmp/lean"
cp -r "$tmp/phantom" "$tmp/default"
mv "$tmp/phantom" "$tmp/staged"
(cd "$tmp/lean" && "$lean_build/bin/vispack-run" config.json --quiet >/dev/null)
(cd "$tmp/default" && "$default_build/bin/vispack-run" config.json --quiet >/dev/null)
# --staged: mask, labels and pack one after another, each reading the work folder's PNGs that the
# stage before wrote (the streaming pass keeps them in memory): the encoder and the decoder in turn.
(cd "$tmp/staged" && "$lean_build/bin/vispack-run" config.json --staged --quiet >/dev/null)
cmp "$tmp/lean/out/volume.vpk" "$tmp/default/out/volume.vpk" ||
  fail "the lean and the default build's packed files differ ($preset, $slices slices)"
cmp "$tmp/staged/out/volume.vpk" "$tmp/default/out/volume.vpk" ||
  fail "the lean build's staged run and the default build's packed files differ"
echo "packed file byte-identical (lean, lean --staged, default): $(sha256sum <"$tmp/lean/out/volume.vpk" | cut -c1-16) ($preset, $slices slices)"
if command -v idiff >/dev/null; then
  pngs=0
  while IFS= read -r png; do
    idiff -q -fail 0 -warn 0 "$tmp/lean/work/$png" "$tmp/default/work/$png" >/dev/null ||
      fail "work/$png: the lean build's pixels differ from the default build's"
    pngs=$((pngs + 1))
  done < <(cd "$tmp/lean/work" && find . -name '*.png' | sort)
  echo "work-folder PNGs with the same pixels: $pngs"
fi

"$lean_build/bin/viewer_bench" --dims 128,96,40 --size 128 --reps 1 --no-paged \
  --ref-png "$tmp/reference.png" >/dev/null
"$lean_build/bin/vispack-view" "$tmp/lean/out/volume.vpk" --screenshot "$tmp/lean.png" \
  --size 160x120 >/dev/null
"$default_build/bin/vispack-view" "$tmp/lean/out/volume.vpk" --screenshot "$tmp/default.png" \
  --size 160x120 >/dev/null
for png in reference.png lean.png; do
  /usr/bin/python3 -c "import sys; from PIL import Image; i = Image.open(sys.argv[1]); i.load(); \
print(sys.argv[1].rsplit('/', 1)[1] + ':', i.mode, i.size)" "$tmp/$png" ||
    fail "$png (written by the lean build) does not read back"
done
if command -v idiff >/dev/null; then
  idiff -q -fail 0 -warn 0 "$tmp/lean.png" "$tmp/default.png" >/dev/null ||
    fail "the lean screenshot's pixels differ from the default build's"
  echo "screenshot: the same pixels as the default build's"
fi

# A JPEG output is refused with one line naming the file, exit 3 (IoError).
set +e
err=$("$lean_build/bin/vispack-phantom" --out "$tmp/jpeg" --preset tiny --seg-jpeg --quiet 2>&1)
code=$?
set -e
[[ $code -eq 3 && $err == *"$tmp/jpeg/seg/"*".jpg: cannot write jpeg: this build has no OpenImageIO"* ]] ||
  fail "lean vispack-phantom --seg-jpeg: exit $code, '$err'"
echo "JPEG output refused: $err"
echo "lean_build: OK"
