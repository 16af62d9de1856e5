#!/usr/bin/env bash
# OME-Zarr export (vispack-export, docs/OME_ZARR.md) against vispack-extract writing the same
# channels and levels as NRRD, on the `vhp` phantom at the real slice size (2048x1216).
# Usage: scripts/bench/ome_zarr_export.sh BIN_DIR WORK_DIR [SLICES] [THREADS] [OUT.json] [ROUNDS]
#   BIN_DIR   folder with vispack-phantom, vispack-run, vispack-export, vispack-extract
#   WORK_DIR  scratch folder (the phantom is generated and packed there once per slice count)
#   SLICES    slices of the phantom, default 128 (2048x1216x128, the figure docs/BENCHMARKS.md
#             records)
#   THREADS   --threads of vispack-export, default 2
#   ROUNDS    rounds, default 3: each round runs every row once, in the order below (interleaved),
#             and each figure is the median over the rounds
# Each command runs under /usr/bin/time -v (wall, CPU, peak resident memory), with the page cache
# warm for the .vpk (one untimed read first). Rows:
#   extract      vispack-extract -o X.nrrd for every channel and level, one after the other (sum)
#   0.4, 0.5     vispack-export --ngff V (all channels and levels); 0.5 with the default shards
#   0.4 no-copy  the same with --no-copy: every chunk decoded and re-encoded (what the copy of
#                stored zstd bricks saves)
# Sizes: the .vpk; each export's bytes (apparent size of every file) and file count; for 0.5 the
# files per shard. Prints a Markdown table; with OUT.json also writes the numbers as JSON (read by
# scripts/bench/report.py, section "OME-Zarr export against NRRD extraction").
set -euo pipefail
shopt -s inherit_errexit  # a failing command inside $(extract_row) or $(export_row) stops the run
bin=${1:?BIN_DIR}
work=${2:?WORK_DIR}
slices=${3:-128}
threads=${4:-2}
json_out=${5:-}
rounds=${6:-3}
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
timev=$root/scripts/bench/time_v.py
mkdir -p "$work"
work=$(realpath "$work")
# shellcheck source=scripts/bench/vhp_phantom.sh
source "$(dirname "${BASH_SOURCE[0]}")/vhp_phantom.sh"
dir=$(vhp_phantom "$bin" "$work" "$slices")
cfg=$dir/config.json
vpk=$(python3 -c 'import json,os,sys; c=json.load(open(sys.argv[1])); print(os.path.normpath(os.path.join(os.path.dirname(sys.argv[1]), c["output"])))' "$cfg")
if [[ ! -f $vpk ]]; then
  python3 -c 'import json,sys; p=sys.argv[1]; j=json.load(open(p)); j.setdefault("vdb", {})["enabled"]=False; json.dump(j, open(p, "w"), indent=1)' "$cfg"
  "$bin/vispack-run" "$cfg" --quiet >/dev/null
fi
out=$work/ome-zarr-bench
rm -rf "$out"
mkdir -p "$out"
cat "$vpk" >/dev/null  # page cache warm for every row alike

channels=$("$bin/vispack-info" "$vpk" --json | python3 -c 'import json,sys; print(" ".join(c["name"] for c in json.load(sys.stdin)["metadata"]["channels"]))')
levels=$("$bin/vispack-info" "$vpk" --json | python3 -c 'import json,sys; print(len(json.load(sys.stdin)["metadata"]["levels"]))')

load_start=$(cut -d' ' -f1-3 /proc/loadavg)

# extract_row: one process per channel and level; prints "wall cpu rss bytes files" (wall and
# CPU summed, peak = the largest).
extract_row() {
  local c l w u r wall=0 cpu=0 rss=0 bytes=0 files=0
  for c in $channels; do
    for ((l = 0; l < levels; ++l)); do
      /usr/bin/time -v "$bin/vispack-extract" "$vpk" --channel "$c" --level "$l" \
        -o "$out/$c-$l.nrrd" 2>"$out/time-extract-$c-$l.txt" >/dev/null
      IFS=, read -r w u r < <(python3 "$timev" "$out/time-extract-$c-$l.txt" wall_s cpu_s peak_rss_mib)
      wall=$(python3 -c "print(round($wall + $w, 2))")
      cpu=$(python3 -c "print(round($cpu + $u, 2))")
      rss=$(python3 -c "print(round(max($rss, $r), 1))")
      bytes=$((bytes + $(stat -c %s "$out/$c-$l.nrrd")))
      files=$((files + 1))
      rm -f "$out/$c-$l.nrrd"
    done
  done
  echo "$wall $cpu $rss $bytes $files"
}

# export_row NAME ARGS...: one export under time -v; prints "wall cpu rss bytes files shards
# chunk_files" (the export stays in $out/NAME.zarr until the next round's).
export_row() {
  local name=$1 dest=$out/$1.zarr
  shift
  rm -rf "$dest"
  /usr/bin/time -v "$bin/vispack-export" "$vpk" --ome-zarr "$dest" --quiet --threads "$threads" "$@" \
    >"$out/stats-$name.txt" 2>"$out/time-$name.txt"
  local tv bytes files shards chunk_files
  tv=$(python3 "$timev" "$out/time-$name.txt" wall_s cpu_s peak_rss_mib |
    awk -F, '{printf "%.2f %.2f %.1f", $1, $2, $3}')
  bytes=$(find "$dest" -type f -printf '%s\n' | awk '{s += $1} END {print s}')
  files=$(find "$dest" -type f | wc -l)
  shards=$(grep -o '([0-9]* shards)' "$out/stats-$name.txt" | tr -dc 0-9)
  chunk_files=$(find "$dest" -type f -path '*/c/*' | wc -l)
  echo "$tv $bytes $files ${shards:-0} $chunk_files"
}

# Round by round, every row once (extract, 0.4, 0.4 no-copy, 0.5): rows.tsv holds one line a
# row and round.
rows=$out/rows.tsv
: >"$rows"
for ((round = 1; round <= rounds; ++round)); do
  row=$(extract_row)
  echo "extract $round $row" >>"$rows"
  row=$(export_row v04 --ngff 0.4)
  echo "v04 $round $row" >>"$rows"
  row=$(export_row v04-nocopy --ngff 0.4 --no-copy)
  echo "v04_nocopy $round $row" >>"$rows"
  row=$(export_row v05 --ngff 0.5)
  echo "v05 $round $row" >>"$rows"
done
load_end=$(cut -d' ' -f1-3 /proc/loadavg)

python3 - "$rows" "$out" "${json_out:-}" "$slices" "$threads" "$rounds" "$(basename "$vpk")" \
  "$(stat -c %s "$vpk")" "$levels" "$channels" "$load_start" "$load_end" <<'PY'
import json, re, statistics, sys
rows, out, json_out, slices, threads, rounds, vpk_name, vpk_bytes, levels, channels, l0, l1 = sys.argv[1:]
slices, threads, rounds, vpk_bytes, levels = map(int, (slices, threads, rounds, vpk_bytes, levels))
keys = ("wall_s", "cpu_s", "peak_mib", "bytes", "files", "shards", "chunk_files")
per = {}
for line in open(rows):
    name, _, *vals = line.split()
    per.setdefault(name, []).append(dict(zip(keys, map(float, vals))))
result = {"slices": slices, "threads": threads, "rounds": rounds, "vpk": vpk_name,
          "vpk_bytes": vpk_bytes, "levels": levels, "channels": channels.split(),
          "load_average_start": [float(x) for x in l0.split()],
          "load_average_end": [float(x) for x in l1.split()]}
for name, runs in per.items():
    row = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
    for k in ("bytes", "files", "shards", "chunk_files"):
        if k in row:
            row[k] = int(runs[-1][k])  # the same every round
    for k in ("wall_s", "cpu_s", "peak_mib"):
        row[k + "_rounds"] = [r[k] for r in runs]
    result[name] = row
def stats(name):
    text = open(f"{out}/stats-{name}.txt").read().strip()
    m = re.search(r"(\d+) chunks copied, (\d+) encoded, (\d+) fill", text)
    return text, dict(zip(("chunks_copied", "chunks_encoded", "chunks_fill"), map(int, m.groups())))
for name in ("v04", "v05"):
    result[name]["stats"], counts = stats(name)
    result[name].update(counts)
result["extract"]["files"] = levels * len(channels.split())
labels = {"extract": "vispack-extract, every channel and level as NRRD",
          "v04": "vispack-export --ngff 0.4", "v04_nocopy": "vispack-export --ngff 0.4 --no-copy",
          "v05": "vispack-export --ngff 0.5"}
print(f"Phantom vhp, {slices} slices ({vpk_name}, {vpk_bytes} bytes, {levels} levels, channels "
      f"{channels}); vispack-export --threads {threads}; medians of {rounds} rounds; load average "
      f"{l0} at the start, {l1} at the end.\n")
print("| run | wall s | CPU s | peak MiB | output bytes | × .vpk | files |")
print("|---|---:|---:|---:|---:|---:|---:|")
for name, label in labels.items():
    r = result[name]
    print(f"| {label} | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | {r['peak_mib']:.1f} | {r['bytes']:,} | "
          f"{r['bytes'] / vpk_bytes:.2f} | {r['files']} |")
v5 = result["v05"]
print(f"\n0.5: {v5['shards']} shard files, {v5['chunk_files']} files under the arrays' c/ folders: "
      f"{v5['chunk_files'] / max(v5['shards'], 1):.2f} files per shard.")
print(f"0.4: {result['v04']['stats']}\n0.5: {v5['stats']}")
if json_out:
    json.dump(result, open(json_out, "w"), indent=1)
PY
