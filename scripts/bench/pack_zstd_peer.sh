#!/bin/bash
# The peer of the pack throughput goal (docs/GOALS.md §6): `zstd -3 -T2` of the raw level-0 bytes of a packed
# file (every channel at level 0 as vispack-extract writes it, NRRD raw, concatenated), timed under
# /usr/bin/time -v; appends one row to scripts/bench/pack_memory.sh's CSV (binary "zstd-3-T2").
# usage: scripts/bench/pack_zstd_peer.sh FILE.vpk CSV [SCRATCH_DIR]
set -euo pipefail
bench_dir=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
here=$(cd "$(dirname "$0")/../.." && pwd)
vpk=$1
csv=$2
scratch=$(mktemp -d "${3:-${TMPDIR:-/tmp}}/pack-zstd-peer-XXXXXX")
trap 'rm -rf "$scratch"' EXIT
extract=${EXTRACT:-$here/build/bin/vispack-extract}
read -r dx dy dz edge < <(/usr/bin/python3 - "$vpk" <<'PY'
import json, struct, sys
f = open(sys.argv[1], "rb")
h = f.read(4096)
# header: magic(8) ... metadata_offset / size at fixed places (format/SPEC.md); use the JSON.
import re
data = open(sys.argv[1], "rb").read()
m = re.search(rb'"dims":\[(\d+),(\d+),(\d+)\]', data[-(1 << 22):])
e = re.search(rb'"brick_edge":(\d+)', data[-(1 << 22):])
print(m.group(1).decode(), m.group(2).decode(), m.group(3).decode(), e.group(1).decode())
PY
)
for ch in rgba ct labels; do
  "$extract" "$vpk" --channel "$ch" -o "$scratch/$ch.nrrd" >/dev/null 2>&1 || true
done
cat "$scratch"/*.nrrd > "$scratch/raw"
rm -f "$scratch"/*.nrrd
/usr/bin/time -v zstd -3 -T2 -q -c "$scratch/raw" 2> "$scratch/time.txt" > "$scratch/raw.zst"
VISPACK_BENCH_DIR=$bench_dir /usr/bin/python3 - "$scratch/time.txt" "$scratch/raw.zst" "$edge" "$dz" "$dx" "$dy" >> "$csv" <<'PY'
import os, sys
sys.path.insert(0, os.environ["VISPACK_BENCH_DIR"])
from time_v import parse_time_v
t = open(sys.argv[1]).read()
tv = parse_time_v(t, sys.argv[1])
edge, dz, dx, dy = sys.argv[3:7]
print(",".join(str(x) for x in ["zstd-3-T2", edge, dz, dx, dy, 7,
                                tv["peak_rss_kib"], tv["user_s"], tv["system_s"], tv["wall_s"],
                                os.path.getsize(sys.argv[2])]))
PY
