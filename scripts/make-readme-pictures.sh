#!/usr/bin/env bash
# Renders vispack-view's default picture of every mode on the small phantom into docs/img/
# (view-MODE.png, shown in the README's viewer section): `vispack-phantom --preset small --seed 7`,
# `vispack-run`, then `vispack-view FILE --mode MODE --size 320x320 --screenshot ...` with no
# other option, so the pictures are what a first-time user sees (docs/GOALS.md §4 "Viewer
# defaults").
# Usage: scripts/make-readme-pictures.sh [--check] [BIN_DIR]      (BIN_DIR default: build/bin)
#   --check  renders into a temporary folder instead and fails, naming the picture, when one
#            differs from the committed docs/img/view-MODE.png by more than 0.1 in more than 1 %
#            of its pixels (OpenImageIO's idiff), so the README's pictures cannot go stale
#            (ctest runs this: viewer.readme_pictures).
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
check=0
bin=$root/build/bin
for arg in "$@"; do
  case $arg in
    --check) check=1 ;;
    -h | --help) sed -n '2,11p' "${BASH_SOURCE[0]}" | cut -c3-; exit 0 ;;
    -*) echo "make-readme-pictures: error: unknown option $arg" >&2; exit 2 ;;
    *) bin=$arg ;;
  esac
done
for tool in vispack-phantom vispack-run vispack-view; do
  [[ -x "$bin/$tool" ]] || { echo "make-readme-pictures: error: $bin/$tool not found (build first)" >&2; exit 3; }
done
if [[ $check == 1 ]] && ! command -v idiff >/dev/null; then
  echo "make-readme-pictures: error: idiff (openimageio-tools) not found: scripts/install-deps.sh" >&2
  exit 3
fi

work=$(mktemp -d "${TMPDIR:-/tmp}/vispack-pictures.XXXXXX")
trap 'rm -rf "$work"' EXIT
"$bin/vispack-phantom" --out "$work/phantom" --preset small --seed 7 >/dev/null 2>&1 ||
  { echo "make-readme-pictures: error: vispack-phantom failed" >&2; exit 1; }
"$bin/vispack-run" "$work/phantom/config.json" --to pack --threads 2 >"$work/run.log" 2>&1 ||
  { cat "$work/run.log" >&2; echo "make-readme-pictures: error: vispack-run failed" >&2; exit 1; }
volume=$work/phantom/out/volume.vpk

out=$root/docs/img
[[ $check == 1 ]] && out=$work/pictures
mkdir -p "$out"
modes=(colour ct labels tf2d iso mip average mpr)
for mode in "${modes[@]}"; do
  shot=$out/view-$mode.png
  if ! "$bin/vispack-view" "$volume" --mode "$mode" --size 320x320 --screenshot "$shot" 2>"$work/view.log"; then
    # No EGL platform here: the same frame through an X server.
    xvfb-run -a "$bin/vispack-view" "$volume" --mode "$mode" --size 320x320 --screenshot "$shot" \
      2>"$work/view.log" || { cat "$work/view.log" >&2; echo "make-readme-pictures: error: $mode" >&2; exit 1; }
  fi
  if [[ $check == 1 ]]; then
    committed=$root/docs/img/view-$mode.png
    if ! idiff -fail 0.1 -failpercent 1 "$shot" "$committed" >"$work/idiff.log" 2>&1; then
      cat "$work/idiff.log" >&2
      echo "make-readme-pictures: error: $committed differs from the default $mode picture: run scripts/make-readme-pictures.sh" >&2
      exit 1
    fi
    echo "view-$mode.png: as committed"
  else
    echo "wrote $shot"
  fi
done
