#!/usr/bin/env bash
# vispack-run --plan, the dry run (pipeline/run/plan.h): for each way an input folder can be
# wrong that a config check cannot see (a raw size, layout or header that does not fit the files,
# a file that is not an image at the end of a folder), --plan fails with the same exit code and
# the same error line as the real run, and writes nothing (no work folder, no output). A sound
# folder plans with exit 0 and one line per input. Usage: plan_dry_run.sh BIN_DIR
set -uo pipefail
bin=$(cd "$1" && pwd)
work=$(mktemp -d "${TMPDIR:-/tmp}/vispack-plan-XXXXXX")
trap 'rm -rf "$work"' EXIT
cd "$work" || exit 1
failed=0
fail() { echo "FAIL: $*"; failed=1; }

"$bin/vispack-phantom" --preset tiny --slices 6 --no-defects --quiet --out png || exit 1
"$bin/vispack-phantom" --preset tiny --slices 6 --no-defects --rgb-raw --quiet --out raw || exit 1

# A sound folder: exit 0, the lines cluster_plan.py reads, one line per input, nothing written.
out=$("$bin/vispack-run" png/config.json --plan 2>&1)
rc=$?
[[ $rc == 0 ]] || fail "sound folder: exit $rc: $out"
for line in "slices 6" "stages register mask labels pack vdb" "pack_slab_slices 64" \
            "input rgb 6 slices, 96 x 64 px, read rgb_0000.png and rgb_0005.png" \
            "input ct 6 slices, 56 x 56 px, read ct_0000.png and ct_0005.png" \
            "input seg 6 slices, 96 x 64 px, read seg_0000.png and seg_0005.png"; do
  grep -qxF "$line" <<<"$out" || fail "sound folder: no line '$line' in: $out"
done
[[ ! -e png/work && ! -e png/out ]] || fail "--plan wrote into png/"

# A colour file missing inside the stack: slabs of output slices (slots) hold fewer files, so no
# fixed count of stack slices makes whole slabs: pack_slab_slices 0 (cluster_plan.py then packs in
# a step of its own).
rm -rf gap && cp -R png gap && rm gap/rgb/rgb_0003.png
out=$("$bin/vispack-run" gap/config.json --plan 2>&1)
rc=$?
[[ $rc == 0 ]] || fail "a colour gap: exit $rc: $out"
for line in "slices 5" "pack_slab_slices 0"; do
  grep -qxF "$line" <<<"$out" || fail "a colour gap: no line '$line' in: $out"
done

# case NAME FOLDER EDIT: copies FOLDER, applies EDIT (bash, in the copy), runs --plan and the real
# run, compares.
case_() {
  local name=$1 folder=$2 edit=$3
  rm -rf "$name" && cp -R "$folder" "$name"
  (cd "$name" && eval "$edit") || { fail "$name: the edit failed"; return; }
  "$bin/vispack-run" "$name/config.json" --plan >"$name.plan.out" 2>"$name.plan.err"
  local plan_rc=$?
  [[ ! -e $name/work && ! -e $name/out ]] || fail "$name: --plan wrote into $name/"
  "$bin/vispack-run" "$name/config.json" --threads 1 >"$name.run.out" 2>"$name.run.err"
  local run_rc=$?
  if [[ $plan_rc == 0 ]]; then
    fail "$name: --plan passed (exit 0), the run gave exit $run_rc: $(<"$name.run.err")"
  # The run's stderr also holds its progress lines; its error line must be --plan's whole stderr.
  elif [[ $plan_rc != "$run_rc" || $(<"$name.plan.err") != "$(grep ': error: ' "$name.run.err")" ]]; then
    fail "$name: --plan exit $plan_rc '$(<"$name.plan.err")', the run exit $run_rc '$(<"$name.run.err")'"
  else
    echo "$name: --plan and the run both exit $plan_rc: $(<"$name.plan.err")"
  fi
}
json_set() {  # json_set KEY.PATH VALUE(JSON) on config.json, with python3's json
  /usr/bin/python3 - "$1" "$2" <<'PY'
import json, sys
c = json.load(open("config.json"))
node = c
*parents, last = sys.argv[1].split(".")
for p in parents:
    node = node[p]
node[last] = json.loads(sys.argv[2])
json.dump(c, open("config.json", "w"), indent=2)
PY
}

case_ raw-width raw 'json_set rgb.raw.width 95'
case_ raw-header raw 'json_set rgb.raw.header_bytes 16'
case_ raw-sixteen-bit raw 'json_set rgb.raw.bits 16'
case_ raw-layout raw 'json_set rgb.raw.layout "\"interleaved\""'
case_ last-rgb-not-an-image png 'echo "not an image" >rgb/rgb_0005.png'
case_ last-ct-empty png ': >ct/ct_0005.png'
case_ last-seg-truncated png 'head -c 100 seg/seg_0005.png >x && mv x seg/seg_0005.png'
case_ rgb-sizes-differ png 'cp ct/ct_0000.png rgb/rgb_0005.png'

exit $failed
