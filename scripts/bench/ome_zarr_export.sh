#!/usr/bin/env bash
# OME-Zarr export (vispack-export, docs/OME_ZARR.md) against vispack-extract writing the same
# channels and levels as NRRD, on the `vhp` phantom at the real slice size (2048x1216).
# Usage: scripts/bench/ome_zarr_export.sh BIN_DIR WORK_DIR [SLICES] [THREADS] [OUT.json]
#   BIN_DIR   folder with vispack-phantom, vispack-run, vispack-export, vispack-extract
#   WORK_DIR  scratch folder (the phantom is generated and packed there once per slice count)
#   SLICES    slices of the phantom, default 128 (2048x1216x128, the figure docs/BENCHMARKS.md
#             records)
#   THREADS   --threads of vispack-export, default 2
# Each command runs under /usr/bin/time -v (wall, CPU, peak resident memory), with the page cache
# warm for the .vpk (one untimed read first). Rows:
#   extract      vispack-extract -o X.nrrd for every channel and level, one after the other (sum)
#   0.4, 0.5     vispack-export --ngff V (all channels and levels); 0.5 with the default shards
#   0.4 no-copy  the same with --no-copy: every chunk decoded and re-encoded (what the copy of
#                stored zstd bricks saves)
# Sizes: the .vpk; each export's bytes (apparent size of every file) and file count; for 0.5 the
# files per shard. Prints a Markdown table; with OUT.json also writes the numbers as JSON.
set -euo pipefail
bin=${1:?BIN_DIR}
work=${2:?WORK_DIR}
slices=${3:-128}
threads=${4:-2}
json_out=${5:-}
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

# extract: one process per channel and level; wall and CPU summed, peak = the largest.
ex_wall=0 ex_cpu=0 ex_rss=0 ex_bytes=0
for c in $channels; do
  for ((l = 0; l < levels; ++l)); do
    /usr/bin/time -v "$bin/vispack-extract" "$vpk" --channel "$c" --level "$l" \
      -o "$out/$c-$l.nrrd" 2>"$out/time-extract-$c-$l.txt" >/dev/null
    IFS=, read -r w u r < <(python3 "$timev" "$out/time-extract-$c-$l.txt" wall_s cpu_s peak_rss_mib)
    ex_wall=$(python3 -c "print(round($ex_wall + $w, 2))")
    ex_cpu=$(python3 -c "print(round($ex_cpu + $u, 2))")
    ex_rss=$(python3 -c "print(round(max($ex_rss, $r), 1))")
    ex_bytes=$((ex_bytes + $(stat -c %s "$out/$c-$l.nrrd")))
    rm -f "$out/$c-$l.nrrd"
  done
done

# row NAME ARGS...: one export under time -v; prints "wall cpu rss bytes files shards".
row() {
  local name=$1 dest=$out/$1.zarr
  shift
  /usr/bin/time -v "$bin/vispack-export" "$vpk" --ome-zarr "$dest" --quiet --threads "$threads" "$@" \
    >"$out/stats-$name.txt" 2>"$out/time-$name.txt"
  local tv bytes files shards
  tv=$(python3 "$timev" "$out/time-$name.txt" wall_s cpu_s peak_rss_mib |
    awk -F, '{printf "%.2f %.2f %.1f", $1, $2, $3}')
  bytes=$(find "$dest" -type f -printf '%s\n' | awk '{s += $1} END {print s}')
  files=$(find "$dest" -type f | wc -l)
  shards=$(grep -o '([0-9]* shards)' "$out/stats-$name.txt" | tr -dc 0-9)
  echo "$tv $bytes $files $shards"
}
read -r v4_wall v4_cpu v4_rss v4_bytes v4_files _ < <(row v04 --ngff 0.4)
read -r nc_wall nc_cpu nc_rss nc_bytes nc_files _ < <(row v04-nocopy --ngff 0.4 --no-copy)
read -r v5_wall v5_cpu v5_rss v5_bytes v5_files v5_shards < <(row v05 --ngff 0.5)
v5_chunk_files=$(find "$out/v05.zarr" -type f -path '*/c/*' | wc -l)
vpk_bytes=$(stat -c %s "$vpk")
stats4=$(cat "$out/stats-v04.txt")
stats5=$(cat "$out/stats-v05.txt")
ratio() { python3 -c "print(f'{$1 / $2:.2f}')"; }

cat <<TABLE
Phantom vhp, $slices slices ($(basename "$vpk"), $vpk_bytes bytes, $levels levels, channels $channels); vispack-export --threads $threads.

| run | wall s | CPU s | peak MiB | output bytes | × .vpk | files |
|---|---:|---:|---:|---:|---:|---:|
| vispack-extract, every channel and level as NRRD | $ex_wall | $ex_cpu | $ex_rss | $ex_bytes | $(ratio "$ex_bytes" "$vpk_bytes") | $((levels * $(wc -w <<<"$channels"))) |
| vispack-export --ngff 0.4 | $v4_wall | $v4_cpu | $v4_rss | $v4_bytes | $(ratio "$v4_bytes" "$vpk_bytes") | $v4_files |
| vispack-export --ngff 0.4 --no-copy | $nc_wall | $nc_cpu | $nc_rss | $nc_bytes | $(ratio "$nc_bytes" "$vpk_bytes") | $nc_files |
| vispack-export --ngff 0.5 | $v5_wall | $v5_cpu | $v5_rss | $v5_bytes | $(ratio "$v5_bytes" "$vpk_bytes") | $v5_files |

0.5: $v5_shards shard files, $v5_chunk_files files under the arrays' c/ folders: $(ratio "$v5_chunk_files" "$v5_shards") files per shard.
0.4: $stats4
0.5: $stats5
TABLE

if [[ -n $json_out ]]; then
  python3 - "$json_out" <<PY
import json, sys
json.dump({"slices": $slices, "threads": $threads, "vpk_bytes": $vpk_bytes, "levels": $levels,
           "extract": {"wall_s": $ex_wall, "cpu_s": $ex_cpu, "peak_mib": $ex_rss, "bytes": $ex_bytes},
           "v04": {"wall_s": $v4_wall, "cpu_s": $v4_cpu, "peak_mib": $v4_rss, "bytes": $v4_bytes, "files": $v4_files},
           "v04_nocopy": {"wall_s": $nc_wall, "cpu_s": $nc_cpu, "peak_mib": $nc_rss, "bytes": $nc_bytes, "files": $nc_files},
           "v05": {"wall_s": $v5_wall, "cpu_s": $v5_cpu, "peak_mib": $v5_rss, "bytes": $v5_bytes, "files": $v5_files,
                   "shards": $v5_shards, "shard_files": $v5_chunk_files}},
          open(sys.argv[1], "w"), indent=1)
PY
fi
