#!/usr/bin/env bash
# scripts/bench/big_machine.sh (the many-core / GPU machine's run) at a toy size, from a bundle
# (scripts/bench/bundle.sh) as a lent machine runs it: every phase runs and says so, the chains'
# packed files agree byte for byte, the viewer's JSON holds level-0 rows of every mode; and a
# deadline too short skips phases with a message instead of failing.
# Usage: big_machine_test.sh BIN_DIR
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)
bin=$(cd "${1:?usage: big_machine_test.sh BIN_DIR}" && pwd)
tmp=$(mktemp -d "${TMPDIR:-/tmp}/vispack-big-machine-test-XXXXXX")
trap 'rm -rf "$tmp"' EXIT
bash "$root/scripts/bench/bundle.sh" "$bin" "$tmp/bundle" >/dev/null
export VISPACK_BIG_PRESET=tiny VISPACK_BIG_SLICES=16 VISPACK_BIG_EDGE=8 VISPACK_BIG_WORKERS="1 2"
export VISPACK_BIG_VIEWER_STACK=256,192,32 VISPACK_BIG_FRAME=24 VISPACK_BIG_REPS=1
export VISPACK_BIG_ROUNDS=1 VISPACK_BIG_GPU_MB=512
export VISPACK_BIG_MACHINE_BENCH="--rounds 1 --mib 8 --compute-steps 1000000 --settle-s 0"
VISPACK_BIG_DEADLINE_S=600 bash "$tmp/bundle/scripts/bench/big_machine.sh" "$tmp/bundle" "$tmp/out"
log=$tmp/out/big_machine.log
for phase in "machine_bench: K workers at best" "viewer, synthetic" "tiny phantom" \
             "cluster chain" "viewer, the chain's file" "pack encoder against zstd"; do
  grep -q "^== $phase.*: done in" "$log" || { echo "phase '$phase' did not end done"; exit 1; }
done
grep -q '^| compute | 8 |' "$log"
grep -q '^chain 2: packed file byte-identical' "$log"
grep -q '^round 1 zstd -3 -T2: wall' "$log"
/usr/bin/python3 - "$tmp/out/viewer-stack.json" "$tmp/out/viewer-stack-footprint.json" \
  "$tmp/out/chains.json" <<'PY'
import json, sys
rows = json.load(open(sys.argv[1]))["paged"]
modes = {r["mode"] for r in rows}
assert modes == {"colour", "ct", "iso", "labels", "mip", "tf2d", "average", "mpr"}, modes
assert all(r["levels"].endswith(" L0") and "," not in r["levels"] for r in rows), rows
# At a 24² frame the footprint asks for coarser levels: --level 0 is what drew level 0 above.
footprint = json.load(open(sys.argv[2]))["paged"]
assert any(r["whole_level"] > 0 for r in footprint), footprint
chains = json.load(open(sys.argv[3]))
assert [c["shards"] for c in chains] == [1, 2], chains
PY
# A deadline too short: the phases past the machine's line are skipped, named, exit 0.
VISPACK_BIG_DEADLINE_S=20 bash "$tmp/bundle/scripts/bench/big_machine.sh" "$tmp/bundle" "$tmp/short" \
  >/dev/null
grep -q '^== cluster chain.*: skipped, [0-9-]* s left' "$tmp/short/big_machine.log"
echo "big_machine: every phase ran from the bundle; a short deadline skips"
