#!/usr/bin/env bash
# The main job on the built-in sample: installs what is missing, builds Release, makes the `small`
# phantom, runs every pipeline stage, renders a picture, and prints where each output is.
# Usage: scripts/demo.sh [OUT]      (default OUT = out/demo)
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
out=${1:-$root/out/demo}
mkdir -p "$out"
out=$(cd "$out" && pwd)
bin=$root/build/bin

step() { printf '\n== %s\n' "$*"; }

step "Installing missing Debian packages"
"$root/scripts/install-deps.sh"

step "Building (Release) into build/"
"$root/scripts/build.sh" "$root/build"

step "Making the small phantom in $out/phantom"
rm -rf "$out/phantom"
"$bin/vispack-phantom" --out "$out/phantom" --preset small --seed 7

step "Running the pipeline (register, mask, labels, pack, vdb)"
"$bin/vispack-run" "$out/phantom/config.json"

packed=$(/usr/bin/python3 -c 'import json,sys,os; c=json.load(open(sys.argv[1])); print(os.path.normpath(os.path.join(os.path.dirname(sys.argv[1]), c.get("output","out/volume.vpk"))))' "$out/phantom/config.json")
vdb=$(/usr/bin/python3 -c 'import json,sys,os; c=json.load(open(sys.argv[1])); print(os.path.normpath(os.path.join(os.path.dirname(sys.argv[1]), c.get("vdb_output","out/volume.vdb"))))' "$out/phantom/config.json")
work=$(/usr/bin/python3 -c 'import json,sys,os; c=json.load(open(sys.argv[1])); print(os.path.normpath(os.path.join(os.path.dirname(sys.argv[1]), c.get("work_dir","work"))))' "$out/phantom/config.json")

step "Checking the packed file"
"$bin/vispack-info" "$packed" --verify

step "Rendering pictures (headless)"
render() {  # render NAME MODE [extra args]
  local name=$1 mode=$2; shift 2
  if [[ -n "${DISPLAY:-}" ]]; then
    "$bin/vispack-view" "$packed" --mode "$mode" --screenshot "$out/$name.png" --size 640x480 "$@"
  else
    "$bin/vispack-view" "$packed" --mode "$mode" --screenshot "$out/$name.png" --size 640x480 "$@" ||
      xvfb-run -a "$bin/vispack-view" "$packed" --mode "$mode" --screenshot "$out/$name.png" --size 640x480 "$@"
  fi
}
# The viewer's defaults: an oblique view, colour and labels with the front half cut away, CT
# windowed to bone (docs/GOALS.md §4 "Viewer defaults").
render render-colour colour
render render-ct ct
render render-labels labels
render render-iso iso

step "Done. Outputs:"
cat <<TXT
  phantom slices + truth   $out/phantom/{rgb,ct,seg,truth}/
  transforms + QC          $work/register/  (transforms.json, qc/; full-size registered slices
                           only with "work": {"write_registered": true} in the config)
  body masks + overlays    $work/mask/  (mask_NNNN.png, overlay_NNNN.png)
  label slices             $work/labels/
  stage reports            $work/*/report.json
  packed volume            $packed   (inspect: build/bin/vispack-info $packed)
  OpenVDB export           $vdb
  rendered pictures        $out/render-{colour,ct,labels,iso}.png
  view it yourself         build/bin/vispack-view $packed
TXT
