#!/bin/bash
# Peak resident memory, CPU and wall time of `vispack-pack --force` against the slice count and the
# brick edge (goal: peak <= one level-0 brick row + 300 MB, flat in the slice count), with an
# optional baseline binary run interleaved with the current one (A B A B per setting).
#
# usage: scripts/bench/pack_memory.sh OUT_DIR "EDGES" PHANTOM_DIR... [-- BASELINE_PACK]
#   PHANTOM_DIR: a phantom folder already run to labels (its config.json), e.g.
#     build/bin/vispack-phantom --out /tmp/vhp128 --preset vhp --slices 128 --seed 1
#     build/bin/vispack-run /tmp/vhp128/config.json --to labels
#   EDGES: brick edges to measure, e.g. "32 64"
# Env: PACK (default build/bin/vispack-pack), THREADS (default 2), REPS (default 1).
# Writes OUT_DIR/pack_memory.csv and, with /usr/bin/python3 + matplotlib, OUT_DIR/pack_memory.png
# and OUT_DIR/pack_memory.md (the table).
set -euo pipefail
bench_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
here=$(cd "$(dirname "$0")/../.." && pwd)
out=$1
edges=$2
shift 2
dirs=()
base=""
while [ $# -gt 0 ]; do
  if [ "$1" = "--" ]; then base=$2; break; fi
  dirs+=("$(cd "$1" && pwd)")
  shift
done
pack=${PACK:-$here/build/bin/vispack-pack}
threads=${THREADS:-2}
reps=${REPS:-1}
mkdir -p "$out"
csv=$out/pack_memory.csv
echo "binary,edge,slices,dx,dy,bytes_per_voxel,peak_rss_kib,user_s,sys_s,wall_s,file_bytes" > "$csv"

measure() {  # binary label, binary, phantom dir, edge
  local label=$1 bin=$2 dir=$3 edge=$4
  local cfg=$dir/config_e$edge.json
  /usr/bin/python3 - "$dir/config.json" "$cfg" "$edge" <<'PY'
import json, sys
c = json.load(open(sys.argv[1]))
c["pack"]["brick_edge"] = int(sys.argv[3])
c["output"] = "out/volume_e%s.vpk" % sys.argv[3]
json.dump(c, open(sys.argv[2], "w"), indent=2)
PY
  local log=$out/time_${label}_$(basename "$dir")_e$edge.txt
  /usr/bin/time -v "$bin" --config "$cfg" --force --quiet --threads "$threads" 2> "$log" > /dev/null
  local vpk=$dir/out/volume_e$edge.vpk
  VISPACK_BENCH_DIR=$bench_dir /usr/bin/python3 - "$log" "$vpk" "$label" "$edge" "$dir" >> "$csv" <<'PY'
import json, os, sys
sys.path.insert(0, os.environ["VISPACK_BENCH_DIR"])
from time_v import parse_time_v
log, vpk, label, edge, d = sys.argv[1:6]
t = open(log).read()
tv = parse_time_v(t, sys.argv[1])
rep = json.load(open(os.path.join(d, "work", "pack", "report.json")))
dims = rep.get("dims") or rep.get("report", {}).get("dims")
cfg = json.load(open(os.path.join(d, "config.json")))
bpv = 4 + (2 if "ct" in cfg else 0) + (1 if "seg" in cfg else 0)  # rgba8 + int16 + uint8 labels
print(",".join(str(x) for x in [label, edge, dims[2], dims[0], dims[1], bpv,
                                tv["peak_rss_kib"], tv["user_s"], tv["system_s"], tv["wall_s"],
                                os.path.getsize(vpk)]))
PY
}

for rep in $(seq "$reps"); do
  for edge in $edges; do
    for dir in "${dirs[@]}"; do
      measure current "$pack" "$dir" "$edge"
      if [ -n "$base" ]; then measure baseline "$base" "$dir" "$edge"; fi
    done
  done
done
/usr/bin/python3 "$here/scripts/bench/pack_memory_plot.py" "$csv" "$out"
