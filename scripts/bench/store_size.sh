#!/usr/bin/env bash
# "Store only what a scene needs": stored size of the packed file against the OpenVDB
# export and `zstd -3` of the raw level-0 bytes, and the work folder against the input, at the
# real slice size. Usage: scripts/bench/store_size.sh BIN_DIR WORK_DIR [SLICES] [OUT.json]
#   BIN_DIR   folder with vispack-phantom, vispack-run, vispack-pack, vispack-extract
#   WORK_DIR  scratch folder (the phantom is generated there once per slice count)
#   SLICES    slices of the `vhp` phantom (2048x1216, colour as planar .raw), default 8
# Prints a Markdown table; with OUT.json also writes the numbers as JSON. Needs zstd, python3.
# Each variant is packed by `vispack-pack --force` from the same intermediates:
#   default   pack.keep_outside_body "none" (colour 0, CT -1024 HU outside the body), no crop
#   keep      "all" (the gel as registered: what the file held before the gel was cleared)
#   crop      default + pack.crop_margin_px 16
# raw level-0 bytes: every channel of a file at level 0 as vispack-extract writes it (NRRD, raw
# encoding), concatenated; `zstd -3 -T1` of those bytes is the peer, always of the same file's own
# bytes (the default file against zstd of the default file's content; the keep file against zstd
# of the keep file's), so both sides hold the same content.
# The OpenVDB export stores wider types (float CT, int32 labels, three floats of colour: 20 bytes
# a voxel against the packed file's int16, uint16 and rgba8: 8 bytes); its ratio is also given
# scaled to the packed file's widths (OpenVDB's standard grids have no 8- or 16-bit types).
# Work folder: with the defaults, and with work.write_registered + work.write_ct (a second run in
# its own work folder, whose packed file must be byte-identical to the default one).
set -euo pipefail
bin=${1:?BIN_DIR}
work=${2:?WORK_DIR}
slices=${3:-8}
json_out=${4:-}
command -v zstd >/dev/null || { echo "store_size.sh: zstd is missing" >&2; exit 1; }
mkdir -p "$work"
work=$(realpath "$work")
# shellcheck source=scripts/bench/vhp_phantom.sh
source "$(dirname "${BASH_SOURCE[0]}")/vhp_phantom.sh"
dir=$(vhp_phantom "$bin" "$work" "$slices")
cfg=$dir/config.json
"$bin/vispack-run" "$cfg" --quiet >/dev/null

# variant NAME EDIT: the phantom's config edited by the Python statement EDIT on `j`, written as
# NAME.json with its own outputs out/NAME.vpk and out/NAME.vdb.
variant() {
  python3 -c '
import json, sys
src, dst, name, edit = sys.argv[1:5]
j = json.load(open(src))
j["output"] = "out/%s.vpk" % name
j["vdb_output"] = "out/%s.vdb" % name
exec(edit)
json.dump(j, open(dst, "w"), indent=2)' "$cfg" "$dir/$1.json" "$1" "$2"
}
variant keep 'j["pack"]["keep_outside_body"] = "all"'
"$bin/vispack-pack" --config "$dir/keep.json" --force --quiet
variant crop 'j["pack"]["crop_margin_px"] = 16'
"$bin/vispack-pack" --config "$dir/crop.json" --force --quiet
variant copies 'j["work_dir"] = "work-copies"; j.setdefault("work", {}).update({"write_registered": True, "write_ct": True})'
"$bin/vispack-run" "$dir/copies.json" --quiet --to pack >/dev/null
cmp -s "$dir/out/copies.vpk" "$dir/out/volume.vpk" && identical=1 || identical=0

# raw_level0 FILE: "RAW_BYTES ZSTD3_BYTES" of FILE's level-0 channels (NRRD, concatenated).
raw_level0() {
  local raw=$work/raw-$slices ch
  rm -rf "$raw" && mkdir -p "$raw"
  for ch in rgba ct labels; do
    "$bin/vispack-extract" "$1" --channel "$ch" -o "$raw/$ch.nrrd" >/dev/null
  done
  echo "$(cat "$raw"/*.nrrd | wc -c) $(cat "$raw"/*.nrrd | zstd -3 -T1 -c | wc -c)"
  rm -rf "$raw"
}
read -r raw_bytes zstd_bytes <<<"$(raw_level0 "$dir/out/volume.vpk")"
read -r raw_keep_bytes zstd_keep_bytes <<<"$(raw_level0 "$dir/out/keep.vpk")"
size() { stat -c %s "$1"; }
du_bytes() { du -sb "$@" | awk '{s += $1} END {print s}'; }

python3 -c '
import json, sys
keys = sys.argv[2::2]
vals = [int(v) for v in sys.argv[3::2]]
r = dict(zip(keys, vals))
r["width"], r["height"] = 2048, 1216
r["packed_identical_with_copies"] = bool(r.pop("identical"))
r["vpk_over_vdb"] = r["vpk_default"] / r["vdb"]
# Bytes per voxel: the packed file as its level-0 bytes say (rgba8 + int16 CT + uint8 or uint16
# labels: 7 or 8); OpenVDB Vec3s + float + int32 = 20.
r["vpk_bytes_per_voxel"] = r["raw_level0"] / (2048 * 1216 * r["slices"])
r["vpk_over_vdb_equal_width"] = r["vpk_over_vdb"] * 20 / r["vpk_bytes_per_voxel"]
r["vpk_over_zstd"] = r["vpk_default"] / r["zstd3_raw_level0"]
r["vpk_keep_over_zstd"] = r["vpk_keep"] / r["zstd3_raw_level0_keep"]
r["vpk_over_input"] = r["vpk_default"] / r["input_bytes"]
r["work_over_input"] = r["work_bytes"] / r["input_bytes"]
r["work_with_copies_over_input"] = r["work_with_copies_bytes"] / r["input_bytes"]
mb = lambda b: "%.1f MB" % (b / 1e6)
print("| what (vhp phantom, 2048x1216, %d slices) | bytes | ratio |" % r["slices"])
print("|---|---|---|")
print("| packed, default (outside body cleared) | %s | %.2fx zstd -3 of its own raw level-0 bytes; %.3fx the input slices |"
      % (mb(r["vpk_default"]), r["vpk_over_zstd"], r["vpk_over_input"]))
print("| packed, default, against the OpenVDB export | | %.2fx (%.2fx at equal type widths: 20 bytes a voxel in the export, %.1f in the packed file) |"
      % (r["vpk_over_vdb"], r["vpk_over_vdb_equal_width"], r["vpk_bytes_per_voxel"]))
print("| packed, crop_margin_px 16 | %s | %.2fx the default |" % (mb(r["vpk_crop"]), r["vpk_crop"] / r["vpk_default"]))
print("| packed, keep_outside_body all (before the gel was cleared) | %s | %.2fx zstd -3 of its own raw level-0 bytes; %.2fx the OpenVDB export |"
      % (mb(r["vpk_keep"]), r["vpk_keep_over_zstd"], r["vpk_keep"] / r["vdb"]))
print("| OpenVDB export (body voxels only) | %s | |" % mb(r["vdb"]))
print("| raw level-0 bytes, default file (all channels) | %s | |" % mb(r["raw_level0"]))
print("| zstd -3 -T1 of the default file raw level-0 bytes | %s | |" % mb(r["zstd3_raw_level0"]))
print("| raw level-0 bytes, keep file | %s | |" % mb(r["raw_level0_keep"]))
print("| zstd -3 -T1 of the keep file raw level-0 bytes | %s | |" % mb(r["zstd3_raw_level0_keep"]))
print("| input folders (rgb .raw, ct, seg) | %s | |" % mb(r["input_bytes"]))
print("| work folder, defaults | %s | %.1f %% of the input |" % (mb(r["work_bytes"]), 100 * r["work_over_input"]))
print("| work folder, write_registered + write_ct | %s | %.1f %% of the input; packed file byte-identical: %s |"
      % (mb(r["work_with_copies_bytes"]), 100 * r["work_with_copies_over_input"],
         "yes" if r["packed_identical_with_copies"] else "NO"))
if sys.argv[1]:
    json.dump(r, open(sys.argv[1], "w"), indent=1)
' "$json_out" slices "$slices" vpk_default "$(size "$dir/out/volume.vpk")" \
  vpk_keep "$(size "$dir/out/keep.vpk")" vpk_crop "$(size "$dir/out/crop.vpk")" \
  vdb "$(size "$dir/out/volume.vdb")" raw_level0 "$raw_bytes" zstd3_raw_level0 "$zstd_bytes" \
  raw_level0_keep "$raw_keep_bytes" zstd3_raw_level0_keep "$zstd_keep_bytes" \
  input_bytes "$(du_bytes "$dir/rgb" "$dir/ct" "$dir/seg")" work_bytes "$(du_bytes "$dir/work")" \
  work_with_copies_bytes "$(du_bytes "$dir/work-copies")" identical "$identical"
[[ $identical == 1 ]] || { echo "store_size.sh: the packed file differs with the work copies" >&2; exit 1; }
